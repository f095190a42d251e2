"""Step time of the realistic 20x20 core per level grid: B = 256, the default observation, random
valid moves, one thread, the grids interleaved round by round (medians of 5 rounds of 1.5 s).

    python docs/reproduction/calibration/time_levels.py 6,8 8,12 12,16 24,16
"""

import sys
import time

import torch
from medc_training.envs import make_batched

torch.set_num_threads(1)
grids = [tuple(int(v) for v in a.split(",")) for a in sys.argv[1:]]
envs = {g: make_batched("target_localization", num_envs=256, seed=0, agents=3, walls=2, grid=20,
                        max_steps=100, sensing={"name": "realistic", "levels": list(g)}) for g in grids}
gen = torch.Generator().manual_seed(0)
masks = {g: e.reset()[1] for g, e in envs.items()}
times = {g: [] for g in grids}
for rnd in range(6):
    for g, e in envs.items():
        t0, n = time.perf_counter(), 0
        while time.perf_counter() - t0 < 1.5:
            m = masks[g]
            a = torch.multinomial(m.float().view(-1, m.shape[-1]), 1, generator=gen).view(m.shape[:-1])
            masks[g] = e.step(a).mask
            n += 1
        if rnd:  # the first round warms up
            times[g].append((time.perf_counter() - t0) / n)
base = sorted(times[grids[0]])[len(times[grids[0]]) // 2]
for g in grids:
    t = sorted(times[g])[len(times[g]) // 2]
    print(f"levels {g}: {t * 1e3:.1f} ms/step, {256 * 3 / t:,.0f} agent-steps/s, x{t / base:.2f}")
