"""Start a run from a trained bundle's network instead of a fresh one (``medc-train --init-from``).

A bundle (a lab's shared model, or an earlier run of one's own) holds the whole actor-critic: the
trunk, the policy head and the value head. A run that starts from it trains on from those weights
with a fresh optimiser and its own schedule (``--lr``, ``--lr-anneal-steps`` count from the run's
step 0). The bundle is read as data (:func:`medc_training.bundle.load_bundle`: safetensors and a
validated manifest, never pickle); it must be for the run's application, take the run's
observation and be the run's architecture (the same tensors with the same shapes), or the run is
refused before it starts, naming what differs.
"""

from __future__ import annotations

from pathlib import Path


def init_from_bundle(learner, path: str | Path) -> dict:
    """Load the network of the bundle at ``path`` into ``learner`` (a single-network learner such as
    :class:`medc_training.ppo.Trainer`) and return its record ``{"bundle": name, "sha256": hex}``.

    Raises:
        ValueError: the learner has no single network (an FRL group), or the bundle is for another
        application, observation or architecture than the run (the message names the difference).
        FileNotFoundError: no file at ``path``.
    """
    from .bundle import BundleError, load_bundle

    net = getattr(learner, "net", None)
    if net is None:
        raise ValueError("--init-from starts one network; an FRL group has one per user "
                         "(train without --init-from, or with another method)")
    source = Path(path)
    if not source.is_file():
        raise FileNotFoundError(f"--init-from: no bundle at {source}")
    try:
        bundle = load_bundle(source)
    except BundleError as exc:
        raise ValueError(f"--init-from: {source} is not a usable bundle: {exc}") from exc
    cfg, env = learner.cfg, learner.env
    if bundle.application != cfg.env:
        raise ValueError(f"--init-from: {source.name} is a {bundle.application} policy; "
                         f"this run trains {cfg.env}")
    wanted_view = getattr(env, "observation_name", None)
    if bundle.observation is not None and wanted_view is not None and bundle.observation != wanted_view:
        raise ValueError(f"--init-from: {source.name} takes the observation {bundle.observation!r}; "
                         f"this run's is {wanted_view!r} (give --observation {bundle.observation})")
    theirs = bundle.net.state_dict()
    ours = net.state_dict()
    differ = sorted(name for name in set(theirs) | set(ours)
                    if name not in theirs or name not in ours or theirs[name].shape != ours[name].shape)
    if differ:
        shown = ", ".join(f"{n} {tuple(theirs[n].shape) if n in theirs else 'missing'} in the bundle vs "
                          f"{tuple(ours[n].shape) if n in ours else 'missing'} in the run"
                          for n in differ[:3])
        raise ValueError(f"--init-from: {source.name} is not this run's network (--arch {cfg.arch}, "
                         f"observation {tuple(learner.obs_shape)}): {shown}"
                         + (f" and {len(differ) - 3} more" if len(differ) > 3 else ""))
    net.load_state_dict({name: t.to(next(net.parameters()).device) for name, t in theirs.items()})
    record = {"bundle": source.name, "sha256": bundle.sha256}
    learner.init_from = record
    return record
