"""Probe: the estimator's levels on geometric bins (equal ratios), each weighted by its bin's share of
the uniform prior; otherwise ``python -m medc_lab.cli.calibrate``.

    python docs/reproduction/calibration/probe_geometric_levels.py sb random --episodes 1000 \\
        --rule declaration --levels 6,8

The first argument says which ranges take geometric bins: ``s`` (strength), ``b`` (background),
``sb`` (both). The equal bins of the other range keep equal weights.
"""

import math
import sys

import torch
from medc_training import calibration
from medc_training.envs import tl_observation, tl_sensing


def edges(bounds, n):
    lo, hi = bounds
    return [lo * (hi / lo) ** (i / n) for i in range(n + 1)]


def geometric(bounds, n, device):
    if n == 1:
        return torch.tensor([bounds[0]], dtype=torch.float32, device=device)
    e = edges(bounds, n)
    return torch.tensor([math.sqrt(e[i] * e[i + 1]) for i in range(n)], dtype=torch.float32, device=device)


def weights(bounds, n):
    if n == 1:
        return [1.0]
    e = edges(bounds, n)
    return [(e[i + 1] - e[i]) / (bounds[1] - bounds[0]) for i in range(n)]


MODE = sys.argv.pop(1)
if "s" in MODE:
    tl_sensing.SensingModel.strength_levels = lambda self, device="cpu": geometric(
        self.strength, self.levels[0], device)
if "b" in MODE:
    tl_sensing.SensingModel.background_levels = lambda self, device="cpu": geometric(
        self.background, self.levels[1], device)
_prior = tl_observation.SourceEstimator.prior


def prior(self, walls):
    p = _prior(self, walls)
    if self.levels == 1:
        return p
    ns, nb = self.sensing.levels
    ws = weights(self.sensing.strength, ns) if "s" in MODE else [1 / ns] * ns
    wb = weights(self.sensing.background, nb) if "b" in MODE else [1 / nb] * nb
    log_w = torch.tensor([math.log(a * b) for a in ws for b in wb], device=p.device)
    free = p > tl_observation.LOG_FLOOR
    p.add_(torch.where(free, log_w.view(1, -1, 1), torch.zeros(())))
    return p


tl_observation.SourceEstimator.prior = prior
raise SystemExit(calibration.main())
