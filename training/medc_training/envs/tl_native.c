/* The source estimator's per-step work in C: one pass per episode instead of about ten torch kernels.
 *
 * medc_training.envs.tl_native builds this file into a shared library and calls it through ctypes
 * on contiguous float32 / int64 / bool torch tensors (tl_observation.SourceEstimator, fused path).
 * Per episode, while its memory is in a core's cache:
 *   medc_levels_update (a posterior over levels, cells-major [cells, levels]): the line of sight of
 *     every reading to every cell; each cell's row of L log-likelihoods, sum_n r_n log rate_n -
 *     S sum_n factor_n - N B (rate and factor looked up per (d², walls crossed) pair), added to the
 *     log posterior, cells ruled out (walls, where an agent stood) floored; the shift by the
 *     episode's maximum and the floor at LOG_FLOOR; the marginal over the levels, normalised;
 *   medc_single_update (one level): walls crossed from the sampled rule's crossing tables, the rate
 *     lookups, the same update and the posterior;
 *   medc_expected_moves: the expected-distance map of a posterior;
 *   medc_factor_moments: the geometric factor's first two moments over a posterior, per candidate
 *     sensor cell (the information map).
 *
 * Built with -O3 -march=x86-64-v2 -fopenmp-simd -ffinite-math-only -fno-signed-zeros -ffp-contract=off
 * (tl_native.FLAGS: no fused multiply-adds, so each product and sum rounds as torch's do; any x86-64
 * machine of the last decade runs it); the hot loops are also cloned for x86-64-v3 (AVX2) and picked
 * at load time where the CPU has it.
 */
#include <stddef.h>
#include <stdint.h>

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

/* For one sensor at `position` (row, col), every cell s of the G×G grid as a candidate source:
 * q = d² + span * k, k the wall rectangles the closed segment from the sensor to s runs through
 * (count) or whether any does, by the separating-axis test in exact arithmetic
 * (tl_sensing._blocked_exact: every quantity a multiple of 1/2 below 2^22, so float32 is exact):
 * the margin min(|dx| hy + |dy| hx - |dx cy - dy cx|, the four side margins) is positive exactly when
 * the segment runs through the open rectangle. */
INLINE void sight_pairs(const int64_t *position, const float *rects, int64_t z, int count, int64_t g,
                        int64_t span, int32_t *restrict q) {
    const float py = (float)position[0], px = (float)position[1];
    const int64_t cells = g * g;
    for (int64_t c = 0; c < cells; ++c) {
        const float dy = (float)(c / g) - py, dx = (float)(c % g) - px;
        q[c] = (int32_t)(dy * dy + dx * dx);
    }
    for (int64_t s = 0; s < z; ++s) {
        const float t = rects[s * 4], l = rects[s * 4 + 1], b = rects[s * 4 + 2], rt = rects[s * 4 + 3];
        const float cy = (t + b) * 0.5f - py, cx = (l + rt) * 0.5f - px;
        const float hy = (b - t) * 0.5f, hx = (rt - l) * 0.5f;
        for (int64_t i = 0; i < g; ++i) {
            const float row = (float)i, dy = row - py;
            const float m_top = (row > py ? row : py) - t, m_bottom = b - (row < py ? row : py);
            int32_t *restrict qi = q + i * g;
            for (int64_t j = 0; j < g; ++j) {
                const float col = (float)j, dx = col - px;
                const float ady = dy < 0.0f ? -dy : dy, adx = dx < 0.0f ? -dx : dx;
                const float cross = dx * cy - dy * cx;
                float m = (adx * hy + ady * hx) - (cross < 0.0f ? -cross : cross);
                m = m < m_top ? m : m_top;
                m = m < m_bottom ? m : m_bottom;
                const float m_left = (col > px ? col : px) - l, m_right = rt - (col < px ? col : px);
                m = m < m_left ? m : m_left;
                m = m < m_right ? m : m_right;
                const int32_t hit = m > 0.0f;
                qi[j] += count ? hit * (int32_t)span : 0;
                if (!count && hit && qi[j] < span) qi[j] += (int32_t)span;
            }
        }
    }
}

/* Steps 1-3 for K episodes.
 *   post      float32 [K, C, L]   log posterior, cells-major, updated in place
 *   log_rate  float32 [Q, L]      log rate of each level per (d², walls crossed) pair q
 *   factor    float32 [Q]         geometric factor A^k / (1 + d²) per pair
 *   strength, background float32 [L]
 *   positions int64 [K, N, 2]     the readings' cells on the G×G grid (C = G²)
 *   rects     float32 [K, Z, 4]   each episode's wall rectangles (top, left, bottom, right)
 *   count     walls crossed are counted (else 0 or 1: whether any is)
 *             the pair of each (episode, reading, cell) is q = d² + span * walls crossed
 *   readings  float32 [K, N]
 *   out       bool [K, C]         cells ruled out
 *   marginal  float32 [K, C] or NULL
 * Returns 0, or 1 when a pair falls outside the tables (nothing after that episode is touched). */
MEDC_CLONES
int medc_levels_update(float *post, const float *log_rate, const float *factor,
                       const float *strength, const float *background, int64_t q_rows,
                       const int64_t *positions, const float *rects, int64_t z, int count, int64_t g,
                       int64_t span, const float *readings, const uint8_t *out, float *marginal,
                       int64_t k, int64_t n, int64_t levels, float dead_cell) {
    const int64_t cells = g * g;
    float top[levels], acc[levels];
    const float *rows[n > 0 ? n : 1];
    int32_t pairs[(n > 0 ? n : 1) * cells];
    for (int64_t e = 0; e < k; ++e) {
        float *restrict block = post + e * cells * levels;
        for (int64_t j = 0; j < n; ++j)
            sight_pairs(positions + (e * n + j) * 2, rects + e * z * 4, z, count, g, span, pairs + j * cells);
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
                const int64_t q = pairs[j * cells + c];
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

/* The moments of the geometric factor over the source posterior, for the information map: for each
 * of M candidate sensor cells of an episode, m1 = sum_s p_s f_q and m2 = sum_s p_s f_q², q the
 * (d², walls crossed) pair of the candidate and source cell s (sight_pairs), f the factor table.
 *   posterior float32 [K, C]; factor float32 [Q]; cand int64 [K, M, 2]; rects float32 [K, Z, 4]
 *   m1, m2    float32 [K, M]
 * Returns 0, or 1 when a pair falls outside the table. */
MEDC_CLONES
int medc_factor_moments(const float *posterior, const float *factor, int64_t q_rows, const int64_t *cand,
                        const float *rects, int64_t z, int count, int64_t g, int64_t span, float *m1,
                        float *m2, int64_t k, int64_t m) {
    const int64_t cells = g * g;
    int32_t pairs[cells];
    for (int64_t e = 0; e < k; ++e) {
        const float *restrict p = posterior + e * cells;
        for (int64_t j = 0; j < m; ++j) {
            sight_pairs(cand + (e * m + j) * 2, rects + e * z * 4, z, count, g, span, pairs);
            double first = 0.0, second = 0.0;
            for (int64_t c = 0; c < cells; ++c) {
                const int32_t q = pairs[c];
                if (q < 0 || q >= q_rows) return 1;
                const double pf = (double)p[c] * (double)factor[q];
                first += pf;
                second += pf * (double)factor[q];
            }
            m1[e * m + j] = (float)first;
            m2[e * m + j] = (float)second;
        }
    }
    return 0;
}

/* exp(x) of a one-level log posterior row, cells at or below EXP_FLOOR exactly 0, normalised. */
INLINE void single_posterior(const float *restrict row, int64_t cells, float *restrict p) {
    float total = 0.0f;
#pragma omp simd reduction(+ : total)
    for (int64_t c = 0; c < cells; ++c) {
        const float x = row[c];
        const float w = x <= EXP_FLOOR ? 0.0f : exp_floored(x < EXP_FLOOR ? EXP_FLOOR : x);
        p[c] = w;
        total += w;
    }
    const float inv = total > 0.0f ? 1.0f / total : 0.0f;
    for (int64_t c = 0; c < cells; ++c) p[c] *= inv;
}

/* The one-level estimator (paper-simple) for K episodes on a G×G grid, C = G² cells, in place:
 * each reading's walls crossed from the sampled rule's crossing tables and the episode's wall
 * segments (tl_sensing.segment_crossings), d² from the positions, the rate and its log looked up per
 * q = crossed * span + d², sum_n (r_n log rate - rate) added to the log posterior, ruled-out cells
 * floored, the episode shifted by its maximum and floored: the torch path's arithmetic in its order,
 * so the log posterior is bit for bit the torch path's; (posterior != NULL) the posterior exp(x),
 * cells at or below EXP_FLOOR exactly 0, normalised.
 *   post      float32 [K, C]
 *   rate, log_rate float32 [Q]
 *   positions int64 [K, N, 2]
 *   table     int8 [2, C, G, 2, C] crossing tables; segments int64 [K, Z, 4] (row0, col0, row1, col1)
 *   readings  float32 [K, N]; out bool [K, C]; posterior float32 [K, C] or NULL
 * Returns 0, or 1 when a pair or a segment falls outside the tables. */
MEDC_CLONES
int medc_single_update(float *post, const float *rate, const float *log_rate, int64_t q_rows, int64_t span,
                       const int64_t *positions, const int8_t *table, const int64_t *segments, int64_t z,
                       const float *readings, const uint8_t *out, float *posterior, int64_t k, int64_t n,
                       int64_t g) {
    const int64_t cells = g * g;
    int32_t crossed[cells];
    float loglik[cells];
    for (int64_t e = 0; e < k; ++e) {
        float *restrict row = post + e * cells;
        const uint8_t *eout = out + e * cells;
        for (int64_t c = 0; c < cells; ++c) loglik[c] = 0.0f;
        for (int64_t j = 0; j < n; ++j) {
            const int64_t pr = positions[(e * n + j) * 2], pc = positions[(e * n + j) * 2 + 1];
            const int64_t cell = pr * g + pc;
            for (int64_t c = 0; c < cells; ++c) crossed[c] = 0;
            for (int64_t s = 0; s < z; ++s) {
                const int64_t *seg = segments + (e * z + s) * 4;
                const int horizontal = seg[0] == seg[2];
                int64_t line = horizontal ? seg[0] : seg[1];
                line = line < 0 ? 0 : line;
                if (line >= g) return 1;
                const int8_t lo = (int8_t)(horizontal ? seg[1] : seg[0]);
                const int8_t hi = (int8_t)(horizontal ? seg[3] : seg[2]);
                const int8_t *span_lo = table + (((int64_t)(!horizontal) * cells + cell) * g + line) * 2 * cells;
                const int8_t *span_hi = span_lo + cells;
                for (int64_t c = 0; c < cells; ++c) crossed[c] += (span_lo[c] <= hi) & (span_hi[c] >= lo);
            }
            const float r = readings[e * n + j];
            for (int64_t i = 0; i < g; ++i) {
                const int64_t dr2 = (i - pr) * (i - pr);
                for (int64_t c = i * g; c < (i + 1) * g; ++c) {
                    const int64_t dc = c - i * g - pc;
                    const int64_t q = crossed[c] * span + dr2 + dc * dc;
                    if (q >= q_rows) return 1;
                    loglik[c] += log_rate[q] * r - rate[q];
                }
            }
        }
        float m = LOG_FLOOR;
        for (int64_t c = 0; c < cells; ++c) {
            const float x = eout[c] ? LOG_FLOOR : row[c] + loglik[c];
            row[c] = x;
            m = x > m ? x : m;
        }
        for (int64_t c = 0; c < cells; ++c) {
            const float x = row[c] - m;
            row[c] = x < LOG_FLOOR ? LOG_FLOOR : x;
        }
        if (posterior) single_posterior(row, cells, posterior + e * cells);
    }
    return 0;
}

/* The posterior of K one-level log posteriors [K, C] (the update's last step alone). */
MEDC_CLONES
void medc_single_posterior(const float *post, int64_t k, int64_t cells, float *posterior) {
    for (int64_t e = 0; e < k; ++e) single_posterior(post + e * cells, cells, posterior + e * cells);
}

/* E(c), the posterior-expected Chebyshev distance from each cell to the source, for K posteriors
 * float32 [K, G²] (rows summing to 1) into expected [K, G²]: max(|dr|, |dc|) = (|du| + |dv|) / 2 on
 * the diagonals u = row + col, v = row - col + G - 1, so E(c) = (A_u(u_c) + A_v(v_c)) / 2 with
 * A_u(x) = sum_u P_u(u) |x - u| over the posterior's marginal on each diagonal, by prefix sums
 * (O(G²) per map). */
MEDC_CLONES
void medc_expected_moves(const float *posterior, int64_t k, int64_t g, float *expected) {
    const int64_t cells = g * g, lines = 2 * g - 1;
    float pu[lines], pv[lines], au[lines], av[lines];
    for (int64_t e = 0; e < k; ++e) {
        const float *p = posterior + e * cells;
        for (int64_t i = 0; i < lines; ++i) pu[i] = pv[i] = 0.0f;
        for (int64_t r = 0; r < g; ++r)
            for (int64_t c = 0; c < g; ++c) {
                pu[r + c] += p[r * g + c];
                pv[r - c + g - 1] += p[r * g + c];
            }
        /* A(0) = sum_i P(i) i; A(x + 1) = A(x) + P(<= x) - P(> x). */
        float su = 0.0f, sv = 0.0f, tu = 0.0f, tv = 0.0f;
        for (int64_t i = 0; i < lines; ++i) {
            su += pu[i] * (float)i;
            sv += pv[i] * (float)i;
            tu += pu[i];
            tv += pv[i];
        }
        float cu = 0.0f, cv = 0.0f;
        for (int64_t x = 0; x < lines; ++x) {
            au[x] = su;
            av[x] = sv;
            cu += pu[x];
            cv += pv[x];
            su += cu - (tu - cu);
            sv += cv - (tv - cv);
        }
        float *out = expected + e * cells;
        for (int64_t r = 0; r < g; ++r)
            for (int64_t c = 0; c < g; ++c) out[r * g + c] = 0.5f * (au[r + c] + av[r - c + g - 1]);
    }
}
