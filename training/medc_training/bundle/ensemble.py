"""Several bundles played as one policy: the move is chosen from the members' mean probabilities.

Members must take the same observation (name and shape), the same actions, the same application and
the same sensing model; each stays untrusted data, loaded and checked as any bundle is. The ensemble
is a :class:`~medc_training.bundle.policy.PolicyBundle` whose network averages the members'
softmax (its logits are the log of that mean, its value the members' mean value), so every
evaluator that takes a bundle takes it; its manifest is the first member's, with
``ensemble`` listing every member's SHA-256. It is not saved as a bundle file.

``medc-radbench A.safetensors+B.safetensors+C.safetensors`` plays one.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import torch

from medc_training.bundle.fileformat import BundleError
from medc_training.bundle.manifest import manifest_prior, manifest_sensing
from medc_training.bundle.policy import PolicyBundle, load_bundle

__all__ = ["MAX_MEMBERS", "EnsembleNet", "ensemble", "load_ensemble"]

#: The most bundles one ensemble holds (each costs a forward pass per decision).
MAX_MEMBERS = 8


class EnsembleNet(torch.nn.Module):
    """The members' networks as one: ``(log mean softmax of their logits, mean value)``."""

    def __init__(self, nets: Sequence[torch.nn.Module]) -> None:
        super().__init__()
        self.members = torch.nn.ModuleList(nets)
        self.obs_shape = nets[0].obs_shape
        self.num_actions = nets[0].num_actions
        self.spec = nets[0].spec

    @torch.no_grad()
    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        probs, values = [], []
        for net in self.members:
            logits, value = net(obs)
            probs.append(torch.softmax(logits, dim=-1))
            values.append(value)
        mean = torch.stack(probs).mean(0)
        return torch.log(mean.clamp_min(1e-12)), torch.stack(values).mean(0)


def ensemble(bundles: Sequence[PolicyBundle]) -> PolicyBundle:
    """One policy from ``bundles`` (2..:data:`MAX_MEMBERS`, module docstring).

    Raises:
        BundleError: too few or too many members, or members that differ in application,
        observation, observation shape, actions or sensing model (the message names the first
        difference and the member).
    """
    if not 2 <= len(bundles) <= MAX_MEMBERS:
        raise BundleError(f"an ensemble holds 2 to {MAX_MEMBERS} bundles, got {len(bundles)}")
    first = bundles[0]
    for k, b in enumerate(bundles[1:], start=2):
        for what, mine, theirs in (
            ("application", b.application, first.application),
            ("observation", b.observation, first.observation),
            ("observation shape", tuple(b.obs_shape), tuple(first.obs_shape)),
            ("actions", b.action_names, first.action_names),
            ("sensing model", manifest_sensing(b.manifest), manifest_sensing(first.manifest)),
            ("background prior", manifest_prior(b.manifest), manifest_prior(first.manifest)),
        ):
            if mine != theirs:
                raise BundleError(f"ensemble member {k} has {what} {mine!r}, member 1 has {theirs!r}; "
                                  "an ensemble's members must agree on it")
    manifest = {**first.manifest, "ensemble": [b.sha256 for b in bundles]}
    net = EnsembleNet([b.net for b in bundles]).eval()
    return dataclasses.replace(first, manifest=manifest, net=net, sha256="+".join(b.sha256 for b in bundles))


def load_ensemble(paths: Sequence[str | Path]) -> PolicyBundle:
    """:func:`ensemble` of the bundles at ``paths``, each loaded and checked by :func:`load_bundle`."""
    if not 2 <= len(paths) <= MAX_MEMBERS:
        raise BundleError(f"an ensemble holds 2 to {MAX_MEMBERS} bundles, got {len(paths)}")
    return ensemble([load_bundle(p) for p in paths])
