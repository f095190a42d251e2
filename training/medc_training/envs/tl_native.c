/* The source estimator's per-step pass over a cells-major posterior over levels, in one loop.
 *
 * medc_training.envs.tl_native builds this file into a shared library and calls it through ctypes
 * on contiguous float32 / int64 / bool torch tensors (tl_observation.SourceEstimator, fused path).
 * Per episode, while its [cells, levels] block is in a core's cache:
 *   1. each cell's row of L log-likelihoods, sum_n r_n log rate_n - S sum_n factor_n - N B (rate
 *      and factor looked up per (d², walls crossed) pair), is added to the log posterior; cells
 *      ruled out (walls, where an agent stood) are floored;
 *   2. the episode is shifted by its maximum and floored at LOG_FLOOR;
 *   3. (marginal != NULL) each cell's sum over the levels of exp(max(x, EXP_FLOOR)); a cell whose
 *      sum is at most dead_cell is exactly 0; the row is normalised to sum 1.
 * The torch path runs the same arithmetic as about ten separate passes over the batch.
 *
 * Built with -O3 -march=x86-64-v2 -fopenmp-simd -ffinite-math-only -fno-signed-zeros (tl_native.FLAGS;
 * any x86-64 machine of the last decade runs it);
 * the hot loops are also cloned for x86-64-v3 (AVX2, FMA) and picked at load time where the CPU
 * has it.
 */
#include <stdint.h>
#include <string.h>

#define LOG_FLOOR (-104.0f)
#define EXP_FLOOR (-87.0f)

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define MEDC_CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define MEDC_CLONES
#endif

/* exp(x) for x in [EXP_FLOOR, 0]: Cody-Waite reduction by ln 2 and a degree-6 polynomial (Cephes'
 * expf coefficients), within 2 ulp of the correctly rounded value; branch-free so loops vectorise. */
static inline float exp_floored(float x) {
    const float t = x * 1.44269504088896341f;
    const int32_t n = (int32_t)(t - 0.5f); /* t <= 0: truncation of t - 1/2 rounds to nearest */
    const float fn = (float)n;
    float r = x - fn * 0.693359375f;
    r = r - fn * -2.12194440e-4f;
    float p = 1.9875691500e-4f;
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    const float y = p * r * r + r + 1.0f;
    union { int32_t i; float f; } scale;
    scale.i = (n + 127) << 23; /* n >= -126 on [EXP_FLOOR, 0]: a normal power of two */
    return y * scale.f;
}

#define INLINE static inline __attribute__((always_inline))

/* acc = a * x (restrict-qualified helpers: the loops vectorise without alias checks). */
INLINE void scaled(float *restrict acc, const float *restrict x, float a, int64_t len) {
    for (int64_t l = 0; l < len; ++l) acc[l] = a * x[l];
}

/* acc += a * x */
INLINE void add_scaled(float *restrict acc, const float *restrict x, float a, int64_t len) {
    for (int64_t l = 0; l < len; ++l) acc[l] += a * x[l];
}

/* row += (acc - fsum * strength) - nf * background; top = max(top, row). */
INLINE void add_loglik(float *restrict row, float *restrict top, const float *restrict acc,
                       const float *restrict strength, const float *restrict background, float fsum,
                       float nf, int64_t len) {
    for (int64_t l = 0; l < len; ++l) {
        const float x = row[l] + ((acc[l] - fsum * strength[l]) - nf * background[l]);
        row[l] = x;
        top[l] = x > top[l] ? x : top[l];
    }
}

/* Shift [cells, levels] by its maximum m, floor at LOG_FLOOR, and (marginal) write each cell's sum
 * over the levels of exp(max(x, EXP_FLOOR)), dead cells 0, normalised. */
INLINE void shift_and_marginal(float *restrict post, float m, int64_t cells, int64_t levels,
                               float *restrict marginal, float dead_cell, int shift) {
    double total = 0.0;
    for (int64_t c = 0; c < cells; ++c) {
        float *restrict row = post + c * levels;
        float sum = 0.0f;
        if (shift) {
#pragma omp simd reduction(+ : sum)
            for (int64_t l = 0; l < levels; ++l) {
                float x = row[l] - m;
                x = x < LOG_FLOOR ? LOG_FLOOR : x;
                row[l] = x;
                sum += exp_floored(x < EXP_FLOOR ? EXP_FLOOR : x);
            }
        } else {
#pragma omp simd reduction(+ : sum)
            for (int64_t l = 0; l < levels; ++l) {
                const float x = row[l];
                sum += exp_floored(x < EXP_FLOOR ? EXP_FLOOR : x);
            }
        }
        if (marginal) {
            sum = sum <= dead_cell ? 0.0f : sum;
            marginal[c] = sum;
            total += sum;
        }
    }
    if (marginal) {
        const float inv = total > 0.0 ? (float)(1.0 / total) : 0.0f;
        for (int64_t c = 0; c < cells; ++c) marginal[c] *= inv;
    }
}

/* Step 3 alone (no update): the marginal posterior of K episodes' cells-major log posteriors. */
MEDC_CLONES
void medc_levels_marginal(const float *post, int64_t k, int64_t cells, int64_t levels,
                          float *marginal, float dead_cell) {
    for (int64_t e = 0; e < k; ++e)
        shift_and_marginal((float *)(post + e * cells * levels), 0.0f, cells, levels,
                           marginal + e * cells, dead_cell, 0);
}

/* Steps 1-3 for K episodes.
 *   post      float32 [K, C, L]   log posterior, cells-major, updated in place
 *   log_rate  float32 [Q, L]      log rate of each level per (d², walls crossed) pair q
 *   factor    float32 [Q]         geometric factor A^k / (1 + d²) per pair
 *   strength, background float32 [L]
 *   d2, crossed int64 [K, N, C]   the pair of each (episode, reading, cell): q = d2 + span * crossed
 *   readings  float32 [K, N]
 *   out       bool [K, C]         cells ruled out
 *   marginal  float32 [K, C] or NULL
 * Returns 0, or 1 when a pair falls outside the tables (nothing after that episode is touched). */
MEDC_CLONES
int medc_levels_update(float *post, const float *log_rate, const float *factor,
                       const float *strength, const float *background, int64_t q_rows,
                       const int64_t *d2, const int64_t *crossed, int64_t span,
                       const float *readings, const uint8_t *out, float *marginal,
                       int64_t k, int64_t n, int64_t cells, int64_t levels, float dead_cell) {
    float top[levels], acc[levels];
    const float *rows[n > 0 ? n : 1];
    for (int64_t e = 0; e < k; ++e) {
        float *restrict block = post + e * cells * levels;
        const int64_t *ed2 = d2 + e * n * cells, *ecr = crossed + e * n * cells;
        const float *r = readings + e * n;
        const uint8_t *eout = out + e * cells;
        for (int64_t l = 0; l < levels; ++l) top[l] = LOG_FLOOR;
        for (int64_t c = 0; c < cells; ++c) {
            float *restrict row = block + c * levels;
            if (eout[c]) {
                for (int64_t l = 0; l < levels; ++l) row[l] = LOG_FLOOR;
                continue;
            }
            float fsum = 0.0f;
            for (int64_t j = 0; j < n; ++j) {
                const int64_t q = ed2[j * cells + c] + span * ecr[j * cells + c];
                if (q < 0 || q >= q_rows) return 1;
                rows[j] = log_rate + q * levels;
                fsum += factor[q];
            }
            /* sum_n r_n log rate_n, reading by reading, then - S sum_n f_n - N B. */
            scaled(acc, rows[0], r[0], levels);
            for (int64_t j = 1; j < n; ++j) add_scaled(acc, rows[j], r[j], levels);
            add_loglik(row, top, acc, strength, background, fsum, (float)n, levels);
        }
        float m = LOG_FLOOR;
        for (int64_t l = 0; l < levels; ++l) m = top[l] > m ? top[l] : m;
        shift_and_marginal(block, m, cells, levels, marginal ? marginal + e * cells : NULL, dead_cell, 1);
    }
    return 0;
}
