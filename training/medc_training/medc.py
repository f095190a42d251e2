"""MEDC action selection (the paper's Algorithm 2, lines 3 and 7-14).

- Per episode: ExpertCheck = rand(); the episode is expert-guided iff ExpertCheck < R_E.
- Per step and per agent of a guided episode: an expert is drawn by roulette wheel over
  R_S; the expert ranks the moves; moves whose probability under the agent's own policy is
  below Q are eliminated; the agent takes the best-ranked remaining move. If none remains,
  the agent samples from its own policy (as in an unguided step).
- The stored log-probability is always the agent's own, log P_k(a), so PPO's ratio stays
  on-policy for the actions the agent would plausibly take itself.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from .experts import Expert


def roulette_wheel(weights: torch.Tensor, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """Draw ``n`` indices with probability proportional to ``weights`` (with replacement)."""
    w = torch.as_tensor(weights, dtype=torch.float64).cpu()
    if w.ndim != 1 or w.numel() == 0:
        raise ValueError(f"roulette wheel needs a non-empty 1-D weight vector, got shape {tuple(w.shape)}")
    if (w < 0).any() or not torch.isfinite(w).all() or w.sum() <= 0:
        raise ValueError(f"roulette wheel weights must be finite, >= 0 and not all 0, got {w.tolist()}")
    if n == 0:
        return torch.zeros(0, dtype=torch.long)
    return torch.multinomial(w, n, replacement=True, generator=generator)


def expert_episode_draw(n: int, expert_rate: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """ExpertCheck < R_E for ``n`` new episodes (bool [n])."""
    return torch.rand(n, generator=generator) < expert_rate


def follow_expert(probs: torch.Tensor, expert_scores: torch.Tensor, mask: torch.Tensor,
                  q: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The Q-threshold rule for M agents.

    Args:
        probs: [M, A] the agent's own (masked) action probabilities P_k.
        expert_scores: [M, A] the expert's ranking (higher = better, -inf = not suggested).
        mask: [M, A] valid moves.
        q: Q; a move is eligible iff P_k(a) >= Q.

    Returns:
        (actions [M] int64, followed [M] bool): the best-ranked eligible move where one
        exists (followed True); -1 where none does (the caller samples from P_k).
    """
    eligible = mask & (probs >= q) & torch.isfinite(expert_scores)
    ranked = expert_scores.masked_fill(~eligible, float("-inf"))
    best = ranked.argmax(dim=-1)
    followed = eligible.any(dim=-1)
    return torch.where(followed, best, torch.full_like(best, -1)), followed


def expert_scores_for(experts: Sequence[Expert], choice: torch.Tensor, obs: torch.Tensor, mask: torch.Tensor,
                      rows: torch.Tensor) -> torch.Tensor:
    """Scores [len(rows), A] where row i is scored by expert ``choice[i]``.

    ``obs``/``mask`` are the full flattened batch [B*N, ...]; ``rows`` indexes it. Each
    expert is called once, on the rows that drew it.
    """
    out = torch.full((rows.numel(), mask.shape[-1]), float("-inf"), device=mask.device)
    for e, expert in enumerate(experts):
        pick = (choice == e).nonzero(as_tuple=True)[0]
        if pick.numel():
            out[pick] = expert.scores_rows(obs, mask, rows[pick].to(obs.device)).to(out.device).float()
    return out
