"""Does the observation carry the answer? Supervised cloning of the oracle as a learnability probe.

Target localization at the CPU scale does not learn from its sparse reward within ~1M PPO
steps (docs/reproduction/report.md). This probe separates "the maps do not tell where the
target is" from "the reward signal is too weak to find out": it records observations along
trajectories that mix the oracle's move and a uniformly random valid move (50/50, so the
states are not only the oracle's), labels every observation with the oracle's best moves, and
fits each architecture by plain supervised learning. A move counts as correct when it is one
of the oracle's equally best moves (ties are common: N and NE can both shorten a path).

    python -m medc_lab.cli.learnability_probe --agents 1 --walls 0 --grid 13 --arch mlp --arch lenet5

Prints one line per quarter of the training, then one JSON line with the held-out accuracies
and the accuracy of always picking a random valid move.
"""

from __future__ import annotations

import argparse
import time

import torch
from medc_training.dagger import best_moves, clone_loss
from medc_training.envs import make_batched
from medc_training.envs.names import TARGET_LOCALIZATION
from medc_training.nets import make_actor_critic, masked_logits


def collect(args: argparse.Namespace, seed: int, steps: int) -> tuple[torch.Tensor, ...]:
    """(obs, mask, oracle scores) of every agent at every step of ``steps`` batched steps."""
    env = make_batched(TARGET_LOCALIZATION, num_envs=args.envs, seed=seed, agents=args.agents,
                       walls=args.walls, grid=args.grid, max_steps=args.max_steps)
    obs, mask = env.reset(seed=seed)
    gen = torch.Generator().manual_seed(seed)
    rows: list[tuple[torch.Tensor, ...]] = []
    for _ in range(steps):
        scores = env.oracle_action_scores()
        rows.append((obs.flatten(0, 1).clone(), mask.flatten(0, 1).clone(), scores.flatten(0, 1).clone()))
        best = scores.masked_fill(~mask, -1e9).argmax(-1)
        rand = torch.multinomial(mask.flatten(0, 1).float(), 1, generator=gen).view(best.shape)
        take_oracle = torch.rand(best.shape, generator=gen) < 0.5
        out = env.step(torch.where(take_oracle, best, rand))
        obs, mask = out.obs, out.mask
    return tuple(torch.cat(parts) for parts in zip(*rows))


def accuracy(net, obs, mask, scores) -> float:
    with torch.no_grad():
        chosen = masked_logits(net(obs)[0], mask).argmax(-1)
    return best_moves(mask, scores).gather(1, chosen[:, None]).float().mean().item()


def probe(args: argparse.Namespace) -> dict:
    """Collect the training and held-out observations, fit each architecture (``args.arch``) by
    supervised cloning of the oracle's best moves, print progress, and return the accuracies."""
    torch.set_num_threads(1)
    train = collect(args, args.seed + 1, args.train_steps)
    test = collect(args, args.seed + 2, max(1, args.train_steps // 8))
    valid = test[1].float()
    chance = ((best_moves(test[1], test[2]).float() * valid).sum(-1) / valid.sum(-1)).mean().item()
    print(f"{train[0].shape[0]} training / {test[0].shape[0]} held-out observations; "
          f"a random valid move is correct {chance:.3f} of the time", flush=True)
    result = {"env": f"A{args.agents}W{args.walls}", "grid": args.grid, "samples": train[0].shape[0],
              "iterations": args.iterations, "random_move_accuracy": round(chance, 4),
              "held_out_accuracy": {}}
    for arch in args.arch or ["mlp", "lenet5"]:
        torch.manual_seed(args.seed)
        net = make_actor_critic(arch, train[0].shape[1:], train[1].shape[-1])
        opt = torch.optim.Adam(net.parameters(), lr=1e-3)
        gen = torch.Generator().manual_seed(args.seed)
        start = time.perf_counter()
        for it in range(1, args.iterations + 1):
            idx = torch.randint(0, train[0].shape[0], (256,), generator=gen)
            loss = clone_loss(net(train[0][idx])[0], train[1][idx], best_moves(train[1][idx], train[2][idx]))
            opt.zero_grad()
            loss.backward()
            opt.step()
            if it % max(1, args.iterations // 4) == 0:
                print(f"{arch:>14} {it:>6} loss {loss.item():.3f} held-out accuracy "
                      f"{accuracy(net, *test):.3f} ({time.perf_counter() - start:.0f}s)", flush=True)
        result["held_out_accuracy"][arch] = round(accuracy(net, *test), 4)
    return result
