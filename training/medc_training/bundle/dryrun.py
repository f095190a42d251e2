"""What a policy costs on this machine, measured before anyone acts with it.

The static caps (``nets.MAX_OPERATIONS``, ``nets.MAX_ACTIVATION_BYTES``) bound a network by its
spec; this module bounds what the arithmetic cannot see:

* **Data-dependent cost.** Float32 subnormal numbers (below ~1.2e-38) take a slow path on many
  CPUs (microcode assists): a net with ~1e-40 weights is fast on a blank observation and slow on a
  real one. Subnormal weights are flushed to 0 when a bundle is loaded
  (:func:`flush_subnormal`: a term below 1.2e-38 changes no output a float32 can show), every
  forward pass of the dry run (and of an agent, :func:`flush_denormals`) runs with the CPU's
  flush-to-zero / denormals-are-zero modes on, and the dry run feeds observations with real
  structure (:func:`dry_run_observations`: the application's own environment, from the manifest's
  scenario, a few steps in; and one dense random observation), not only a blank one.
* **A slow bundle under the caps.** The dry run goes layer by layer (:func:`timed_forward`) and stops
  as soon as the time spent, or the time a large layer is about to take (estimated from running it
  on a strip of its output first), passes the limit: a bundle too slow to act with is refused after
  about the limit, never after several full passes.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator, Mapping
from functools import lru_cache
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

#: A conv2d or maxpool2d layer costing more operations than this (one observation) is first run on
#: a strip of its output rows and its full time extrapolated; the shipped architectures' largest
#: layer costs ~3 M, so they are always run as they are.
PROBE_OPERATIONS = 4_000_000
#: The strip a probed layer is run on: this fraction of its output rows (at least one).
PROBE_FRACTION = 1 / 16
#: Environment steps taken (random allowed moves) before the structured dry-run observation.
DRY_RUN_STEPS = 3

_TINY = torch.finfo(torch.float32).tiny  # smallest normal float32, ~1.18e-38


class TooSlow(Exception):
    """A timed forward pass went (or was about to go) over its limit; ``seconds`` says how far."""

    def __init__(self, seconds: float, estimated: bool, layer: int | None) -> None:
        super().__init__(seconds)
        self.seconds, self.estimated, self.layer = seconds, estimated, layer


def flush_subnormal(tensor: torch.Tensor) -> torch.Tensor:
    """``tensor`` (float32) with every subnormal value set to 0, in place; returns it."""
    tensor.masked_fill_((tensor != 0) & (tensor.abs() < _TINY), 0.0)
    return tensor


def _flushing() -> bool:
    """Whether this thread's CPU flushes subnormal results to zero now (a product that would be
    ~5e-39 comes out 0)."""
    return float(torch.tensor([2e-38], dtype=torch.float32).mul(0.25)) == 0.0


@contextlib.contextmanager
def flush_denormals() -> Iterator[None]:
    """Run the body with the CPU's flush-to-zero and denormals-are-zero modes on in this thread
    (``torch.set_flush_denormal``; a no-op where the CPU has none), restoring the previous mode:
    training code outside it keeps IEEE subnormals."""
    was = _flushing()
    if not was:
        torch.set_flush_denormal(True)
    try:
        yield
    finally:
        if not was:
            torch.set_flush_denormal(False)


def _layer_operations(module: nn.Module, x: torch.Tensor) -> int:
    """Multiply-adds (or compared window elements) of a conv2d / maxpool2d on ``x`` [M,C,H,W]."""
    m, c, h, w = x.shape
    k = module.kernel_size if isinstance(module.kernel_size, int) else module.kernel_size[0]
    s = module.stride if isinstance(module.stride, int) else module.stride[0]
    p = module.padding if isinstance(module.padding, int) else module.padding[0]
    oh, ow = max(0, (h + 2 * p - k) // s + 1), max(0, (w + 2 * p - k) // s + 1)
    per_out = c * k * k * (module.out_channels if isinstance(module, nn.Conv2d) else 1)
    return m * per_out * oh * ow


def _run_strip(module: nn.Module, part: torch.Tensor, stride: int) -> float:
    """Seconds ``module`` (a conv2d, already padded, or a maxpool2d) takes on the rows ``part``."""
    start = time.perf_counter()
    if isinstance(module, nn.Conv2d):
        F.conv2d(part, module.weight, module.bias, stride=stride)
    else:
        F.max_pool2d(part, module.kernel_size, stride=stride)
    return time.perf_counter() - start


def _probe_seconds(module: nn.Module, x: torch.Tensor, budget: float = float("inf")) -> float | None:
    """Estimated seconds of ``module`` (a conv2d or maxpool2d) on ``x``: its time on the first
    ``PROBE_FRACTION`` of its output rows, scaled up; None when the layer is too small to probe.

    An estimate over ``budget`` (the time left before the limit) is taken only if a second run of
    the strip confirms it (the faster of the two counts): on a shared machine one strip can be
    stalled for tens of milliseconds, which scaled up by the strip's fraction would refuse a bundle
    that is not slow. A slow layer pays one more strip (a sixteenth of the layer) to be refused."""
    if _layer_operations(module, x) <= PROBE_OPERATIONS:
        return None
    k, s = module.kernel_size, module.stride
    k = k if isinstance(k, int) else k[0]
    s = s if isinstance(s, int) else s[0]
    if isinstance(module, nn.Conv2d):
        p = module.padding if isinstance(module.padding, int) else module.padding[0]
        x = F.pad(x, (p, p, p, p))
    rows_out = (x.shape[2] - k) // s + 1
    strip = max(1, int(rows_out * PROBE_FRACTION))
    if strip >= rows_out:
        return None
    part = x[:, :, :(strip - 1) * s + k, :]
    scale = rows_out / strip
    seconds = _run_strip(module, part, s)
    if seconds * (scale + 1) > budget:  # the estimate plus the strip's own time, as the caller counts them
        seconds = min(seconds, _run_strip(module, part, s))
    return seconds * scale


def timed_forward(net: nn.Module, obs: torch.Tensor, mask: torch.Tensor, limit_s: float) -> float:
    """Seconds one greedy decision of the actor-critic ``net`` (``medc_training.nets.ActorCritic``)
    takes on ``obs`` [M,C,H,W] with ``mask`` [M,A], layer by layer, with flush-to-zero on.

    Raises:
        TooSlow: the time so far, or so far plus a large layer's estimate, passed ``limit_s``: the
        pass is abandoned there (so a slow network costs about ``limit_s``, not a full pass).
    """
    from medc_training.nets import masked_logits

    spent = 0.0
    with torch.no_grad(), flush_denormals():
        x = obs
        for i, module in enumerate(net.trunk):
            if isinstance(module, nn.Conv2d | nn.MaxPool2d):
                start = time.perf_counter()
                estimate = _probe_seconds(module, x, limit_s - spent)
                spent += time.perf_counter() - start
                if estimate is not None and spent + estimate > limit_s:
                    raise TooSlow(spent + estimate, True, i)
            start = time.perf_counter()
            x = module(x)
            spent += time.perf_counter() - start
            if spent > limit_s:
                raise TooSlow(spent, False, i)
        start = time.perf_counter()
        logits = net.policy(x)
        net.value(x)
        masked_logits(logits, mask).argmax(dim=-1)
        if obs.device.type == "cuda":
            torch.cuda.synchronize(obs.device)
        spent += time.perf_counter() - start
    if spent > limit_s:
        raise TooSlow(spent, False, None)
    return spent


def dry_run_observations(manifest: Mapping[str, Any], obs_shape: tuple[int, int, int]) -> list[torch.Tensor]:
    """Observations [1,C,H,W] to time a policy on: a blank one (and the first, cold, call), one its
    application's environment makes (the manifest's scenario and observation variant, a few
    random steps in: walls, team, readings, visits, estimate as an agent sees them) when the
    manifest's scenario can be built and gives this shape, and a dense random one (every input
    non-zero)."""
    shape = tuple(int(v) for v in obs_shape)
    out = [torch.zeros((1, *shape))]
    real = _environment_observation(scenario_key(manifest))
    if real is not None and tuple(real.shape[1:]) == shape:
        out.append(real)
    out.append(torch.rand((1, *shape), generator=torch.Generator().manual_seed(0)))
    return out


def scenario_key(manifest: Mapping[str, Any]) -> tuple:
    """What of a manifest the dry run's environment observation depends on: (application,
    observation name, integer environment attributes)."""
    env = manifest.get("environment") or {}
    return (str(manifest.get("application")), (manifest.get("observation") or {}).get("name"),
            tuple(sorted((k, v) for k, v in env.items() if isinstance(v, int) and not isinstance(v, bool))))


@lru_cache(maxsize=8)
def _environment_observation(key: tuple) -> torch.Tensor | None:
    """Agent 0's observation in the scenario ``key`` (application, observation name, integer
    environment attributes) after ``DRY_RUN_STEPS`` random moves; None when it cannot be built
    (an unknown option, a scenario the environment refuses). Sensing is the default preset: the
    observation's structure, not the sensor's numbers, is what matters here."""
    from medc_training.envs import core_options, make_batched

    app, name, items = key
    try:
        allowed = set(core_options(app)) - {"copy_obs", "posterior", "sensing", "noise", "reward_shaping"}
        options = {k: v for k, v in items if k in allowed}
        if name is not None and "observation" in allowed:
            options["observation"] = name
        env = make_batched(app, num_envs=1, device="cpu", seed=0, **options)
        obs, mask = env.reset()
        gen = torch.Generator().manual_seed(0)
        for _ in range(DRY_RUN_STEPS):
            actions = torch.multinomial(mask[0].float(), 1, generator=gen).view(1, -1)
            step = env.step(actions)
            obs, mask = step.obs, step.mask
        return obs[0, :1].clone()
    except Exception:  # any scenario the environment cannot build: the other observations remain
        return None
