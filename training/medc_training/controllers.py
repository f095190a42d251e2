"""Classical search controllers for target localization: what a radiation-search user would field
instead of a learned team, as first-class policies.

Each is a pure batched function of the team's state (team memory, positions, move mask, walls,
sensing model) returning move scores float32 [B,N,8], -inf where a move is invalid, so the core, the
PettingZoo env and a ROS agent node call it on their own team memory. :func:`controller_policy`
makes one an evaluator policy; :data:`SEARCHERS` adds :mod:`medc_training.searchers`. Each rule,
its source and its approximations: docs/training.md, "The controllers' rules".
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import torch

from medc_training.envs.grid import action_deltas, grid_cells
from medc_training.envs.tl_sensing import SensingModel, geometric_factor, parse_sensing
from medc_training.move_scores import at_cells as _at
from medc_training.move_scores import choose_move as _choose
from medc_training.move_scores import expected_chebyshev
from medc_training.move_scores import neighbour_cells as _neighbours
from medc_training.searchers import STATS

__all__ = [
    "CONTROLLERS",
    "COORDINATED",
    "SEARCHERS",
    "controller_policy",
    "controller_scores",
    "expected_chebyshev",
    "first_episodes",
    "gradient_scores",
    "greedy_scores",
    "infotaxis_scores",
    "posterior_mean_levels",
]

#: The information-driven searchers of :mod:`medc_training.searchers`: name -> options of
#: :func:`~medc_training.searchers.searcher_scores`.
SEARCHERS: dict[str, dict] = {
    "infotaxis-exact": {"criterion": "entropy"},
    "space-aware": {"criterion": "space-aware"},
    "infotaxis-2step": {"criterion": "entropy", "depth": 2},
    "team-infotaxis": {"criterion": "entropy", "coordinated": True},
    "team-space-aware": {"criterion": "space-aware", "coordinated": True},
}
#: The controllers' names, as :func:`controller_policy` and ``medc-controllers`` take them.
CONTROLLERS: tuple[str, ...] = ("gradient", "greedy", "infotaxis", *SEARCHERS)
#: The controllers that read the team's source posterior.
NEEDS_POSTERIOR: frozenset[str] = frozenset({"greedy", "infotaxis", *SEARCHERS})
#: The controllers whose agents choose in turn (agent i's move depends on agents 0 .. i-1's).
COORDINATED: frozenset[str] = frozenset(k for k, v in SEARCHERS.items() if v.get("coordinated"))
#: chi-squared(2 dof) 95% point: a window's slope below it is not told apart from counting noise.
WALD_FLAT = 5.99
#: Elements per chunk of the infotaxis tensors (candidate moves x cells x count values).
_CHUNK_ELEMENTS = 1 << 22


# ------------------------------------------------------------------------------------------
# shared pieces
# ------------------------------------------------------------------------------------------


def posterior_mean_levels(log_post: torch.Tensor,
                          sensing: SensingModel | str) -> tuple[torch.Tensor, torch.Tensor]:
    """(strength, background) float32 [B]: their posterior means under the team's joint log
    posterior (float32 [B,L,G²] levels-first, or [B,G²] when both are known), as
    :class:`~medc_training.envs.tl_observation.SourceEstimator` keeps it."""
    sensing = parse_sensing(sensing)
    b, dev = log_post.shape[0], log_post.device
    level_s, level_b = sensing.level_values(dev)
    if log_post.dim() == 2:
        return level_s[0].expand(b).clone(), level_b[0].expand(b).clone()
    w = torch.logsumexp(log_post, dim=2)  # [B,L]
    w = torch.softmax(w, dim=1)
    return w @ level_s, w @ level_b


def _as_batch(value: torch.Tensor | float | None, b: int, device: torch.device,
              default: float) -> torch.Tensor:
    if value is None:
        value = default
    return torch.as_tensor(value, dtype=torch.float32, device=device).expand(b).clone()


# ------------------------------------------------------------------------------------------
# the three controllers
# ------------------------------------------------------------------------------------------


def greedy_scores(posterior: torch.Tensor, positions: torch.Tensor, mask: torch.Tensor,
                  visit_map: torch.Tensor | None = None) -> torch.Tensor:
    """Move scores float32 [B,N,8]: minus the posterior-expected Chebyshev distance to the source
    from each neighbour (module docstring); -inf where ``mask`` is False.

    posterior float32 [B,G²] (the team's source posterior, rows summing to 1); positions int64
    [B,N,2]; mask bool [B,N,8]; visit_map float32 [B,G,G] (tie-break; none: ties by action index).
    """
    g = math.isqrt(posterior.shape[1])
    cells = _neighbours(positions, g)
    e = _at(expected_chebyshev(posterior, g), cells)  # [B,N,8]
    visits = torch.zeros_like(e) if visit_map is None else _at(visit_map, cells)
    return _choose(-e, mask, [(e, 1e-4), (visits, 0.0)])


def gradient_scores(reading_map: torch.Tensor, visit_map: torch.Tensor, positions: torch.Tensor,
                    mask: torch.Tensor, sensing: SensingModel | str, *,
                    background: torch.Tensor | float | None = None, radius: int = 2,
                    noise: bool | None = None) -> torch.Tensor:
    """Move scores float32 [B,N,8] of gradient search (module docstring); -inf where invalid.

    reading_map float32 [B,G,G] (the team's latest normalised reading per cell, as
    :func:`~medc_training.envs.tl_sensing.update_memory` writes it); visit_map float32 [B,G,G] (raw
    visit counts; 0 = no reading); positions int64 [B,N,2]; mask bool [B,N,8]; ``sensing`` the
    model the readings were made under (their scale); ``background`` float32 [B] or a number
    (counts/s; default: the middle of the model's range); ``radius`` of the fitting window;
    ``noise`` whether readings are Poisson counts (default: the model's ``noise``): with noise-free
    readings any determined slope counts. Where the slope is determined, the score of a move is the
    component of the normalised gradient along it (per cell); where flat, minus the neighbour's
    visit count.
    """
    sensing = parse_sensing(sensing)
    noise = sensing.noise if noise is None else bool(noise)
    b, n = positions.shape[:2]
    g = reading_map.shape[-1]
    dev = reading_map.device
    bg = _as_batch(background, b, dev, 0.5 * sum(sensing.background))
    visited = (visit_map > 0).to(torch.float32)
    counts = torch.expm1(reading_map * math.log1p(sensing.max_rate)) * visited
    r = int(radius)
    side = 2 * r + 1
    maps = torch.stack((counts, visited), dim=1)  # [B,2,G,G]
    padded = torch.nn.functional.pad(maps, (r, r, r, r))
    gp = g + 2 * r
    offs = torch.arange(side, device=dev)
    rows = positions[..., 0:1] + offs
    cols = positions[..., 1:2] + offs
    idx = (rows.unsqueeze(-1) * gp + cols.unsqueeze(-2)).view(b, 1, n * side * side).expand(b, 2, -1)
    win = padded.view(b, 2, gp * gp).gather(2, idx).view(b, 2, n, side * side)
    y, w = win[:, 0], win[:, 1]  # [B,N,K]
    d = (offs - r).to(torch.float32)
    dr = d.repeat_interleave(side)  # row offset of each window cell
    dc = d.repeat(side)
    cnt = w.sum(-1)
    safe = cnt.clamp(min=1.0)
    mr, mc, my = (w * dr).sum(-1) / safe, (w * dc).sum(-1) / safe, (w * y).sum(-1) / safe
    xr, xc, yy = (dr - mr.unsqueeze(-1)) * w, (dc - mc.unsqueeze(-1)) * w, (y - my.unsqueeze(-1)) * w
    srr, scc, src = (xr * xr).sum(-1), (xc * xc).sum(-1), (xr * xc).sum(-1)
    sry, scy = (xr * yy).sum(-1), (xc * yy).sum(-1)
    det = srr * scc - src * src
    determined = (cnt >= 3) & (det > 1e-6 * (srr + scc).clamp(min=1.0) ** 2)
    safe_det = torch.where(determined, det, torch.ones_like(det))
    gr = (scc * sry - src * scy) / safe_det
    gc = (srr * scy - src * sry) / safe_det
    if noise:  # Wald statistic of the slope against Poisson noise of the window's level
        wald = (gr * (srr * gr + src * gc) + gc * (src * gr + scc * gc)) / my.clamp(min=1.0)
        determined &= wald >= WALD_FLAT
    else:
        determined &= (gr.abs() + gc.abs()) > 1e-4 * my.clamp(min=1.0)
    # The level at the agent's cell (the plane at offset 0), without the background.
    level = my - gr * mr - gc * mc - bg.unsqueeze(1)
    scale = 1.0 / level.clamp(min=1.0)
    deltas = action_deltas(dev).to(torch.float32)
    unit = deltas / deltas.norm(dim=-1, keepdim=True)  # [8,2]
    along = (gr * scale).unsqueeze(-1) * unit[:, 0] + (gc * scale).unsqueeze(-1) * unit[:, 1]  # [B,N,8]
    visits = _at(visit_map, _neighbours(positions, g))
    det_ = determined.unsqueeze(-1)
    score = torch.where(det_, along, -visits)
    key = torch.where(det_, -along, visits)
    tol = torch.where(det_, 1e-4 * along.abs().amax(-1, keepdim=True).clamp(min=1e-6), 0.0)
    # The visit tie-break applies in both cases (after the slope where it is determined).
    return _choose(score, mask, [(key, tol), (visits, 0.0)])


def infotaxis_scores(posterior: torch.Tensor, positions: torch.Tensor, mask: torch.Tensor,
                     walls: torch.Tensor, sensing: SensingModel | str, *,
                     strength: torch.Tensor | float | None = None,
                     background: torch.Tensor | float | None = None, visit_map: torch.Tensor | None = None,
                     rects: torch.Tensor | None = None, quantiles: int = 5) -> torch.Tensor:
    """Move scores float32 [B,N,8]: minus the expected posterior entropy (nats) after each move and
    its reading (module docstring); -inf where invalid.

    posterior float32 [B,G²]; positions int64 [B,N,2]; mask bool [B,N,8]; walls bool [B,G,G];
    ``sensing`` the team's sensor model; ``strength``/``background`` float32 [B] or numbers
    (counts/s; default: the middle of the model's ranges; :func:`posterior_mean_levels` gives the
    team's estimates); visit_map float32 [B,G,G] (tie-break); rects the episode's wall rectangles
    (:func:`~medc_training.envs.tl_sensing.wall_rectangles`, for the exact line rule; made from
    ``walls`` when None); ``quantiles`` K, the count values per move.
    """
    sensing = parse_sensing(sensing)
    b, g2 = posterior.shape
    n = positions.shape[1]
    g = math.isqrt(g2)
    dev = posterior.device
    s_est = _as_batch(strength, b, dev, 0.5 * sum(sensing.strength))
    b_est = _as_batch(background, b, dev, 0.5 * sum(sensing.background))
    cells_nb = _neighbours(positions, g)  # [B,N,8,2]
    m = n * 8
    cand = cells_nb.view(b, m, 2)
    every = grid_cells(g, dev)  # [G²,2]
    k = int(quantiles)
    probs = (torch.arange(k, device=dev, dtype=torch.float32) + 0.5) / k
    out = torch.empty((b, m), device=dev)
    # Chunk over episodes so that the [rows, M, G², K] temporaries stay small.
    # The sampled line rule takes 2G samples per (candidate, cell) pair.
    per_row = m * g2 * max(k, 2 * g if sensing.line == "sampled" else 1)
    rows_per = max(1, _CHUNK_ELEMENTS // max(1, per_row))
    for lo in range(0, b, rows_per):
        sl = slice(lo, min(b, lo + rows_per))
        p = posterior[sl]
        f = geometric_factor(sensing, cand[sl], every, walls[sl], None if rects is None else rects[sl])
        lam = s_est[sl].view(-1, 1, 1) * f + b_est[sl].view(-1, 1, 1)  # [R,M,G²]
        delta = cand[sl].unsqueeze(2) - every  # [R,M,G²,2]
        near = sensing.within_reach((delta * delta).sum(-1))
        pm = p.unsqueeze(1).expand_as(lam)
        p_found = (pm * near).sum(-1)  # [R,M]
        q = pm.masked_fill(near, 0.0)
        q = q / q.sum(-1, keepdim=True).clamp(min=1e-30)
        # Weighted quantiles of the rate under the not-found posterior -> the count values.
        lam_sorted, order = lam.sort(-1)
        cum = q.gather(-1, order).cumsum(-1)
        pos = torch.searchsorted(cum.contiguous(), probs.expand(*cum.shape[:-1], k).contiguous())
        counts = lam_sorted.gather(-1, pos.clamp(max=g2 - 1)).round()  # [R,M,K]
        # log Poisson(r; lam_s) for every count value and source cell: [R,M,K,G²]
        log_lam = lam.log()
        ll = counts.unsqueeze(-1) * log_lam.unsqueeze(2) - lam.unsqueeze(2)
        ll = ll - torch.lgamma(counts + 1).unsqueeze(-1)
        STATS["likelihood_terms"] += ll.numel()
        log_q = torch.log(q.clamp(min=1e-38)).masked_fill(q <= 0, float("-inf")).unsqueeze(2)
        joint = ll + log_q  # log q(s) P(r | s)
        log_pr = torch.logsumexp(joint, -1, keepdim=True)  # log predictive P(r_k)
        post = torch.exp(joint - log_pr)
        h = -(post * (joint - log_pr).clamp(min=-1e30)).nan_to_num(0.0).sum(-1)  # [R,M,K]
        wk = torch.softmax(log_pr.squeeze(-1), -1)
        # Where the move finds the source for certain, nothing is left to learn (no NaN from 0/0).
        rest = (wk * h).sum(-1).nan_to_num(0.0, posinf=0.0, neginf=0.0)
        out[sl] = (1.0 - p_found).clamp(min=0.0) * rest
    expected_h = out.view(b, n, 8)
    e = _at(expected_chebyshev(posterior, g), cells_nb)
    visits = torch.zeros_like(e) if visit_map is None else _at(visit_map, cells_nb)
    return _choose(-expected_h, mask, [(expected_h, 1e-4), (e, 1e-4), (visits, 0.0)])


# ------------------------------------------------------------------------------------------
# as policies of a batched core, and their evaluation
# ------------------------------------------------------------------------------------------


def controller_scores(name: str, env, mask: torch.Tensor | None = None, envs: torch.Tensor | None = None,
                      **options) -> torch.Tensor:
    """float32 [B,N,8]: controller ``name``'s move scores for the current state of the batched
    target-localization core ``env`` (it reads the core's team memory, positions, walls and mask;
    ``options`` go to the controller's function). ``envs`` (int64 [K], optional): score only those
    environments, [K,N,8] (``mask`` is then theirs, [K,N,8], or None for the core's), spending
    nothing on the others. Raises ValueError for an unknown name, a core of another
    application, or a posterior-reading controller on a core that keeps no posterior."""
    _check(name, env)
    mem = env.memory

    def pick(value):  # the chosen environments' rows of a per-environment tensor
        return value if envs is None or not isinstance(value, torch.Tensor) else value[envs]

    if mask is None:
        mask = pick(env.mask)
    positions, walls, visits = pick(env.positions), pick(env.walls), pick(mem.visit_map)
    rects = pick(mem.rects) if mem.sensing.line == "exact" else None
    if name in SEARCHERS:
        from medc_training.searchers import searcher_scores

        return searcher_scores(pick(mem.log_post), positions, mask, walls, mem.sensing, rects=rects,
                               visit_map=visits, **SEARCHERS[name], **options)
    if name == "greedy":
        return greedy_scores(pick(mem.posterior()), positions, mask, visits, **options)
    if mem.log_post is not None:
        strength, background = posterior_mean_levels(mem.log_post, mem.sensing)
    else:
        strength, background = None, _background_floor(env)
    strength, background = pick(strength), pick(background)
    if name == "gradient":
        options.setdefault("noise", env.noise)
        return gradient_scores(pick(mem.reading_map), visits, positions, mask, mem.sensing,
                               background=background, **options)
    return infotaxis_scores(pick(mem.posterior()), positions, mask, walls, mem.sensing, strength=strength,
                            background=background, visit_map=visits, rects=rects, **options)


def _background_floor(env) -> torch.Tensor:
    """float32 [B]: without a posterior, the background as the team's lowest reading so far, within
    the model's background range (the known background when the model has one)."""
    mem = env.memory
    lo, hi = mem.sensing.background
    counts = torch.expm1(mem.reading_map * math.log1p(mem.sensing.max_rate))
    lowest = counts.masked_fill(mem.visit_map <= 0, float("inf")).flatten(1).amin(1)
    return lowest.clamp(min=lo, max=hi)


def _check(name: str, env) -> None:
    if name not in CONTROLLERS:
        raise ValueError(f"unknown controller {str(name)[:40]!r}; choose one of {', '.join(CONTROLLERS)}")
    from medc_training.envs import APPLICATIONS

    app = APPLICATIONS.get(getattr(env, "name", None))
    if app is None or not app.controllers or not hasattr(env, "memory"):
        playable = ", ".join(n.replace("_", " ") for n, a in APPLICATIONS.items() if a.controllers)
        raise ValueError(f"the {name} controller plays {playable} (a batched core made with make_batched), "
                         f"not {getattr(env, 'name', env)!r}")
    if name in NEEDS_POSTERIOR and env.memory.log_post is None:
        raise ValueError(f"the {name} controller reads the team's source posterior, but this core keeps "
                         f"none (observation {env.observation_name!r} shows no estimate); make the core "
                         "with posterior=True, e.g. make_batched(..., posterior=True)")


def controller_policy(name: str, env, **options) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """Controller ``name`` as an evaluator :data:`~medc_training.evaluate.Policy` on the batched core
    ``env``: logits [B*N, 8] (the controller's scores; argmax = its move) for the core's current
    state, whatever observation it is handed. Play it greedily (``play(env, policy)``, the default).
    Raises ValueError as :func:`controller_scores` does, at once."""
    _check(name, env)

    def policy(obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        b, n, a = env.num_envs, env.num_agents, env.num_actions
        scores = controller_scores(name, env, mask.view(b, n, a).to(env.device), **options)
        return scores.reshape(b * n, a)

    policy.controller = name  # type: ignore[attr-defined]
    return policy


def first_episodes(env, policy=None, seed: int = 12345) -> dict:
    """Play the first episode of every environment of ``env`` to its end (reset from ``seed``) through
    :func:`~medc_training.evaluate.play_episodes`: ``episodes`` (= num_envs), ``success_rate``, mean
    ``episode_length``, ``seconds`` (wall) and, for a policy, ``decisions_per_s`` (agent moves decided
    per second of the policy's own time). ``policy`` None = uniformly random valid moves."""
    from medc_training.evaluate import play_episodes

    spent = [0.0, 0]
    timed = None
    if policy is not None:
        def timed(obs, mask):
            start = time.perf_counter()
            logits = policy(obs, mask)
            if logits.is_cuda:
                torch.cuda.synchronize(logits.device)
            spent[0] += time.perf_counter() - start
            spent[1] += mask.shape[0]
            return logits

    start = time.perf_counter()
    played = play_episodes(env, timed, episodes=env.num_envs, seed=seed)
    result = {
        "episodes": env.num_envs,
        "success_rate": sum(played.successes) / env.num_envs,
        "episode_length": sum(played.lengths) / env.num_envs,
        "seconds": time.perf_counter() - start,
    }
    if policy is not None:
        result["decisions_per_s"] = spent[1] / max(spent[0], 1e-9)
    return result
