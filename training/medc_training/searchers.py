"""Information-driven searchers on the team's full posterior: infotaxis with the source's strength and
the background marginalised, space-aware infotaxis, two-step infotaxis and their coordinated team
versions. :mod:`medc_training.controllers` registers them as controllers (``infotaxis-exact``,
``space-aware``, ``infotaxis-2step``, ``team-infotaxis``, ``team-space-aware``), so each plays
wherever a controller does: the evaluator, ``medc-radbench``, ``medc-agent -p policy:=NAME`` and
``medc-launch --policy NAME``. The belief they use, the quadrature over the counts, each criterion
with its source, the team's turn order and the cost: docs/training.md, "The information-driven
searchers".
"""

from __future__ import annotations

import math

import torch

from medc_training.envs.grid import action_deltas, grid_cells, move_mask, pad_blocked
from medc_training.envs.tl_observation import EXP_FLOOR
from medc_training.envs.tl_sensing import SensingModel, geometric_factor, parse_sensing
from medc_training.move_scores import at_cells as _at
from medc_training.move_scores import choose_move as _choose
from medc_training.move_scores import expected_chebyshev
from medc_training.move_scores import neighbour_cells as _neighbours

__all__ = [
    "CRITERIA",
    "LEVEL_MASS",
    "QUADRATURE",
    "STATS",
    "TEAM_QUADRATURE",
    "TWO_STEP_BRANCHES",
    "Belief",
    "expected_criterion",
    "searcher_scores",
]

#: Count values per move in the expectation over a reading.
QUADRATURE = 6
#: Count values per teammate's reading (team searchers) and per first outcome (two-step infotaxis).
TEAM_QUADRATURE = 3
#: First moves a two-step searcher expands.
TWO_STEP_BRANCHES = 3
#: Levels kept hold all but this posterior mass in every row.
LEVEL_MASS = 1e-6
#: The criteria: "entropy" (infotaxis) and "space-aware".
CRITERIA = ("entropy", "space-aware")
#: Elements per chunk of the [rows, moves, counts, hypotheses] temporaries.
_CHUNK_ELEMENTS = 1 << 22
#: Bins of the rate's histogram and points of the count grid that place the quadrature's counts.
_RATE_BINS, _COUNT_GRID = 48, 128
_LN2 = math.log(2.0)
#: Work counter: likelihood terms (hypothesis x count value x candidate move) evaluated since the
#: caller last reset it; ``medc-radbench --cost`` reports it per decision.
STATS = {"likelihood_terms": 0}


class Belief:
    """A batch of beliefs over hypotheses (level, cell): ``logp`` float32 [R, L', G²] normalised log
    probabilities (-inf where a hypothesis has no mass), the levels' ``strength`` and ``background``
    float32 [R, L'] and ``row`` int64 [R], the episode (of the walls and rects) each belief is about.
    Several beliefs can be about one episode (a teammate's outcomes)."""

    def __init__(self, logp: torch.Tensor, strength: torch.Tensor, background: torch.Tensor,
                 row: torch.Tensor) -> None:
        self.logp, self.strength, self.background, self.row = logp, strength, background, row

    @staticmethod
    def from_log_post(log_post: torch.Tensor, sensing: SensingModel) -> Belief:
        """The team's belief from its estimator's log posterior (float32 [B,L,G²], or [B,G²] when
        the strength and background are known), levels pruned (:data:`LEVEL_MASS`)."""
        b, dev = log_post.shape[0], log_post.device
        if log_post.dim() == 2:  # known strength and background: one level
            log_post = log_post.unsqueeze(1)
        level_s, level_b = sensing.level_values(dev)
        if log_post.shape[1] != len(level_s):
            raise ValueError(f"the log posterior has {log_post.shape[1]} levels, the sensing model "
                             f"{sensing.levels[0]} x {sensing.levels[1]} = {len(level_s)}")
        logp = log_post.masked_fill(log_post <= EXP_FLOOR, float("-inf"))
        logp = logp - torch.logsumexp(logp.flatten(1), 1).view(b, 1, 1)
        level_mass = torch.logsumexp(logp, 2).exp()  # [B, L]
        order = level_mass.argsort(1, descending=True)
        left = 1.0 - level_mass.gather(1, order).cumsum(1)  # mass outside the first j + 1 levels
        keep = int((left > LEVEL_MASS).sum(1).max()) + 1
        keep = min(keep, logp.shape[1])
        top = order[:, :keep]
        logp = logp.gather(1, top.unsqueeze(-1).expand(-1, -1, logp.shape[2]))
        logp = logp - torch.logsumexp(logp.flatten(1), 1).view(b, 1, 1)
        return Belief(logp, level_s[top], level_b[top], torch.arange(b, device=dev))


def _count_values(lam: torch.Tensor, logq: torch.Tensor, k: int) -> torch.Tensor:
    """float32 [R,M,K]: strictly increasing integer count values for the quadrature over a reading
    whose rate is ``lam`` [R,M,H] under the (not-found) log posterior ``logq`` [R,M,H] (module
    docstring)."""
    rmax = float(lam.amax()) if lam.numel() else 0.0
    dev = lam.device
    if rmax + 8.0 * math.sqrt(rmax) + 8.0 < k:  # every count with weight: 0 .. K-1, exact
        return torch.arange(k, device=dev, dtype=torch.float32).expand(*lam.shape[:2], k).contiguous()
    # The predictive's quantiles, to place the points: the rate's distribution under q on a log
    # histogram (48 bins), each bin's Poisson spread taken as normal; its CDF on a grid of counts.
    edges = torch.logspace(-1.0, math.log10(max(rmax, 1.0)) + 1e-3, _RATE_BINS + 1, device=dev)
    centres = (edges[1:] * edges[:-1]).sqrt()
    bins = torch.bucketize(lam, edges[1:-1])  # 0 .. _RATE_BINS - 1
    weight = torch.zeros((*lam.shape[:2], _RATE_BINS), device=dev).scatter_add_(2, bins, logq.exp())
    weight = weight / weight.sum(2, keepdim=True).clamp(min=1e-30)
    grid = torch.linspace(0.0, math.sqrt(rmax) + 5.0, _COUNT_GRID, device=dev) ** 2  # counts
    spread = torch.special.ndtr((grid.view(1, -1) + 0.5 - centres.view(-1, 1)) / centres.sqrt().view(-1, 1))
    cdf = (weight @ spread).contiguous()  # [R,M,grid]
    probs = (torch.arange(k, device=dev, dtype=torch.float32) + 0.5) / k
    pos = torch.searchsorted(cdf, probs.expand(*cdf.shape[:2], k).contiguous())
    counts = grid[pos.clamp(max=_COUNT_GRID - 1)].round()
    steps = torch.arange(k, device=dev, dtype=torch.float32)
    return torch.cummax(counts - steps, dim=2).values.clamp(min=0.0) + steps  # strictly increasing


def _widths(counts: torch.Tensor) -> torch.Tensor:
    """float32 [...,K]: the count values' cell widths (midpoints to the neighbours; the end cells
    mirrored), all 1 for consecutive integers."""
    if counts.shape[-1] == 1:
        return torch.ones_like(counts)
    first = 2 * counts[..., :1] - counts[..., 1:2]
    last = 2 * counts[..., -1:] - counts[..., -2:-1]
    padded = torch.cat((first, counts, last), -1)
    return 0.5 * (padded[..., 2:] - padded[..., :-2])


class _Outcomes:
    """The outcomes of moves to ``cand`` [R,M,2] from beliefs ``belief`` (module docstring):
    ``p_found`` [R,M]; ``logw`` [R,M,K] the count values' normalised log weights; ``logpost``
    [R,M,K,L',G²] the normalised log posterior after each (not found, count value)."""

    def __init__(self, belief: Belief, cand: torch.Tensor, walls: torch.Tensor, rects: torch.Tensor | None,
                 sensing: SensingModel, k: int) -> None:
        r, m = cand.shape[:2]
        logp = belief.logp  # [R,L,G²]
        g2 = logp.shape[2]
        g = math.isqrt(g2)
        cells = grid_cells(g, cand.device)
        rows = belief.row
        f = geometric_factor(sensing, cand, cells, walls[rows], None if rects is None else rects[rows])
        lam = torch.addcmul(belief.background.view(r, 1, -1, 1), f.unsqueeze(2),
                            belief.strength.view(r, 1, -1, 1))  # [R,M,L,G²]
        delta = cand.unsqueeze(2) - cells  # [R,M,G²,2]
        near = sensing.within_reach((delta * delta).sum(-1)).unsqueeze(2)  # [R,M,1,G²]
        lp = logp.unsqueeze(1)  # [R,1,L,G²]
        p_found = (lp.exp() * near).sum((2, 3)).clamp(0.0, 1.0)  # [R,M]
        logq = lp.masked_fill(near, float("-inf"))
        logq = logq - torch.logsumexp(logq.flatten(2), 2).view(r, m, 1, 1).clamp(min=-1e30)
        flat_lam, flat_q = lam.flatten(2), logq.flatten(2)
        counts = _count_values(flat_lam, flat_q, k)  # [R,M,K]
        # log q_h + log Poisson(k; lambda_h), for every count value and hypothesis: [R,M,K,H]
        joint = counts.unsqueeze(-1) * flat_lam.log().unsqueeze(2) - flat_lam.unsqueeze(2)
        joint = joint - torch.lgamma(counts + 1.0).unsqueeze(-1) + flat_q.unsqueeze(2)
        STATS["likelihood_terms"] += joint.numel()
        log_pk = torch.logsumexp(joint, -1)  # [R,M,K]: log P(k)
        self.logpost = (joint - log_pk.unsqueeze(-1)).view(r, m, k, *logp.shape[1:])
        logw = log_pk + _widths(counts).log()
        self.logw = logw - torch.logsumexp(logw, -1, keepdim=True)
        self.p_found = p_found


def _chebyshev_from(cand: torch.Tensor, grid: int) -> torch.Tensor:
    """float32 [R,M,G²]: moves (Chebyshev distance) from each candidate cell to every cell."""
    return (cand.unsqueeze(2) - grid_cells(grid, cand.device)).abs().amax(-1).to(torch.float32)


def _criterion(logpost: torch.Tensor, cand: torch.Tensor, criterion: str) -> torch.Tensor:
    """float32 [R,M,K]: the criterion of each posterior ``logpost`` [R,M,K,L,G²] (normalised over
    its last two dimensions), the agent standing at ``cand`` [R,M,2]."""
    cell = torch.logsumexp(logpost, 3)  # [R,M,K,G²]: log p(c)
    p = cell.exp()
    entropy = -(p * cell).nan_to_num(0.0, posinf=0.0, neginf=0.0).sum(-1) / _LN2  # bits
    if criterion == "entropy":
        return entropy
    g = math.isqrt(cell.shape[-1])
    moves = (p * _chebyshev_from(cand, g).unsqueeze(2)).sum(-1)
    return torch.log2((moves + torch.exp2(entropy - 1.0) - 0.5).clamp(min=1.0))


def expected_criterion(belief: Belief, weight: torch.Tensor, cand: torch.Tensor, walls: torch.Tensor,
                       rects: torch.Tensor | None, sensing: SensingModel, criterion: str = "entropy",
                       quadrature: int = QUADRATURE) -> torch.Tensor:
    """float32 [R,M]: the expected criterion after a move to each candidate ``cand`` [R,M,2] from
    each belief, weighed by ``weight`` [R] (the belief's probability; 0 = none), chunked by rows."""
    r, m = cand.shape[:2]
    per_row = m * quadrature * belief.logp[0].numel()
    step = max(1, _CHUNK_ELEMENTS // max(1, per_row))
    out = torch.empty((r, m), device=cand.device)
    for lo in range(0, r, step):
        sl = slice(lo, min(r, lo + step))
        part = Belief(belief.logp[sl], belief.strength[sl], belief.background[sl], belief.row[sl])
        o = _Outcomes(part, cand[sl], walls, rects, sensing, quadrature)
        j = _criterion(o.logpost, cand[sl], criterion)
        rest = (o.logw.exp() * j).sum(-1).nan_to_num(0.0, posinf=0.0, neginf=0.0)
        out[sl] = weight[sl].unsqueeze(1) * (1.0 - o.p_found) * rest
    return out


def _outcome_beliefs(belief: Belief, weight: torch.Tensor, cell: torch.Tensor, walls: torch.Tensor,
                     rects: torch.Tensor | None, sensing: SensingModel,
                     k: int) -> tuple[Belief, torch.Tensor]:
    """The beliefs after a move of one agent to ``cell`` [R,2] from each belief: R*K beliefs (belief
    i's outcomes at rows i*K .. i*K + K-1, not found and each count value) and their weights [R*K]
    (``weight`` times the probability of not finding, times the count value's weight)."""
    o = _Outcomes(belief, cell.unsqueeze(1), walls, rects, sensing, k)
    r = cell.shape[0]
    # A certain finding leaves no not-found posterior (NaN): such a belief has weight 0 and no mass.
    logp = o.logpost[:, 0].reshape(r * k, *belief.logp.shape[1:]).nan_to_num(nan=float("-inf"))
    w = (weight.unsqueeze(1) * (1.0 - o.p_found) * o.logw[:, 0].exp()).reshape(-1).nan_to_num(0.0)
    rep = lambda t: t.repeat_interleave(k, 0)  # noqa: E731
    return Belief(logp, rep(belief.strength), rep(belief.background), rep(belief.row)), w


def _two_step(belief: Belief, cand: torch.Tensor, valid: torch.Tensor, one: torch.Tensor, walls: torch.Tensor,
              rects: torch.Tensor | None, sensing: SensingModel, quadrature: int) -> torch.Tensor:
    """float32 [R,M]: the two-step expected entropy of the first moves ``cand`` [R,M,2] (valid [R,M]),
    given their one-step values ``one`` [R,M] (module docstring: the best TWO_STEP_BRANCHES are
    expanded)."""
    r, m = cand.shape[:2]
    dev = cand.device
    branches = min(TWO_STEP_BRANCHES, m)
    ranked = one.masked_fill(~valid, float("inf")).argsort(1)[:, :branches]  # [R,P]
    out = one.clone()
    g = walls.shape[-1]
    k2 = TEAM_QUADRATURE
    for j in range(branches):
        first = cand.gather(1, ranked[:, j:j + 1].unsqueeze(-1).expand(-1, -1, 2))[:, 0]  # [R,2]
        after, w = _outcome_beliefs(belief, torch.ones(r, device=dev), first, walls, rects, sensing, k2)
        second = _neighbours(first, g).repeat_interleave(k2, 0)  # [R*K,8,2]
        # The second moves the environment allows from the first move's cell: [R*K,8]
        ok = move_mask(first.unsqueeze(1), pad_blocked(walls[belief.row]), action_deltas(dev))[:, 0]
        ok = ok.repeat_interleave(k2, 0)
        e2 = expected_criterion(after, torch.ones(r * k2, device=dev), second, walls, rects, sensing,
                                "entropy", quadrature)
        best = e2.masked_fill(~ok, float("inf")).amin(1)  # [R*K]
        best = torch.where(torch.isfinite(best), best, torch.zeros_like(best))
        value = (w * best).view(r, k2).sum(1)  # the found branch adds 0
        out.scatter_(1, ranked[:, j:j + 1], value.unsqueeze(1))
    return out


def searcher_scores(log_post: torch.Tensor, positions: torch.Tensor, mask: torch.Tensor, walls: torch.Tensor,
                    sensing: SensingModel | str, *, criterion: str = "entropy", depth: int = 1,
                    coordinated: bool = False, rects: torch.Tensor | None = None,
                    visit_map: torch.Tensor | None = None, quadrature: int = QUADRATURE) -> torch.Tensor:
    """Move scores float32 [B,N,8]: minus the expected criterion after each move (module docstring);
    -inf where ``mask`` is False; the chosen move raised just above the rest (controllers' tie rule).

    log_post: the team estimator's log posterior (float32 [B,L,G²], or [B,G²]); positions int64
    [B,N,2]; mask bool [B,N,8]; walls bool [B,G,G]; ``sensing`` the team's model; ``criterion``
    "entropy" or "space-aware"; ``depth`` 1 or 2 (entropy only); ``coordinated``: agents choose in
    turn, each conditioning on its teammates' chosen moves; rects the episodes' wall rectangles (the
    exact line rule; made from ``walls`` when None); visit_map float32 [B,G,G] (tie-break).
    """
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {', '.join(CRITERIA)}, got {criterion!r}")
    if depth not in (1, 2) or (depth == 2 and (criterion != "entropy" or coordinated)):
        raise ValueError("depth is 1, or 2 for infotaxis (entropy) without coordination")
    sensing = parse_sensing(sensing)
    b, n = positions.shape[:2]
    g = walls.shape[-1]
    dev = positions.device
    belief = Belief.from_log_post(log_post, sensing)
    weight = torch.ones(b, device=dev)
    cand_all = _neighbours(positions, g)  # [B,N,8,2]
    posterior = torch.logsumexp(belief.logp, 1).exp()  # [B,G²]
    e = _at(expected_chebyshev(posterior, g), cand_all)
    visits = torch.zeros_like(e) if visit_map is None else _at(visit_map, cand_all)
    if not coordinated:
        rows = belief.row.repeat_interleave(n)
        flat = Belief(belief.logp.repeat_interleave(n, 0), belief.strength.repeat_interleave(n, 0),
                      belief.background.repeat_interleave(n, 0), rows)
        cand = cand_all.reshape(b * n, 8, 2)
        value = expected_criterion(flat, weight.repeat_interleave(n), cand, walls, rects, sensing, criterion,
                                   quadrature)
        if depth == 2:
            value = _two_step(flat, cand, mask.reshape(b * n, 8), value, walls, rects, sensing, quadrature)
        value = value.view(b, n, 8)
        return _choose(-value, mask, [(value, 1e-4), (e, 1e-4), (visits, 0.0)])
    out = torch.empty((b, n, 8), device=dev)
    for i in range(n):
        branches = belief.row.shape[0] // b  # beliefs per episode, episode-major
        cand = cand_all[:, i].repeat_interleave(branches, 0)  # [R,8,2]
        v = expected_criterion(belief, weight, cand, walls, rects, sensing, criterion, quadrature)
        v = v.view(b, branches, 8).sum(1)  # the teammates' finding branches add 0
        scores = _choose(-v.unsqueeze(1), mask[:, i:i + 1], [(v.unsqueeze(1), 1e-4), (e[:, i:i + 1], 1e-4),
                                                             (visits[:, i:i + 1], 0.0)])
        out[:, i] = scores[:, 0]
        if i + 1 < n:
            move = scores[:, 0].argmax(-1)  # [B]
            chosen = cand_all[torch.arange(b, device=dev), i, move]  # [B,2]
            if not bool(mask[:, i].any(-1).all()):  # an agent with no valid move stays
                chosen = torch.where(mask[:, i].any(-1, keepdim=True), chosen, positions[:, i])
            # Episode-major again: the rows of episode e are its branches times the new outcomes.
            belief, weight = _outcome_beliefs(belief, weight, chosen.repeat_interleave(branches, 0), walls,
                                              rects, sensing, TEAM_QUADRATURE)
    return out
