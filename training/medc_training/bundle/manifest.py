"""The bundle manifest: its schema, how a saved bundle's manifest is completed, and how a stored
one is validated (every claim cross-checked against the others and against the architecture).

What an application's observations are is asked of its descriptor
(:func:`medc_training.envs.application`), never decided by its name.
"""

from __future__ import annotations

import json
import math
import subprocess
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import medc_training
from medc_training.bundle.fileformat import BundleError
from medc_training.envs import APPLICATIONS, ENV_NAMES, Application
from medc_training.nets import ActorCritic, SpecError, safe_names, safe_repr, validate_spec

FORMAT = "medc-policy-bundle"
FORMAT_VERSION = 1

# A bundle for an application this code does not know (not in medc_training.envs.APPLICATIONS)
# cannot be run by it, so it is rejected rather than guessed at.
KNOWN_APPLICATIONS: tuple[str, ...] = tuple(ENV_NAMES)
#: The largest ``environment.grid`` and ``environment.agents`` a bundle may name. An agent node
#: builds its team memory for the grid and subscribes to every agent's topics *from the manifest*,
#: before any weight is used, so these bound what one file can make an agent allocate: its memory
#: grows faster than G^2 (measured for the ROS agent's observer, init + first reading, paper-simple
#: sensing: +20 MB at 30, +57 MB at 64, +330 MB at 128, +2.5 GB at 256), and 10^6 would need
#: terabytes. 64 is the largest grid any of the three environments is used with (fleet coordination
#: and maze cleaning accept no more; every shipped and reproduced bundle is on 10-30) and the most
#: agents target localization accepts.
MAX_BUNDLE_GRID = 64
MAX_BUNDLE_AGENTS = 64
_MANIFEST_KEYS = {
    "format", "format_version", "application", "description", "environment", "observation",
    "actions", "architecture", "training", "metrics",
}


def _application(app: Any) -> Application | None:
    """The descriptor of a known application, else None."""
    return APPLICATIONS.get(app) if isinstance(app, str) else None


def _names_view(app: Any) -> bool:
    """Whether ``app`` is a known application whose bundles always name their view (those made
    before view names took 'maps') and whose view fixes the channel names."""
    desc = _application(app)
    return desc is not None and desc.manifest_names_view


def complete_manifest(net: ActorCritic, manifest: Mapping[str, Any]) -> dict[str, Any]:
    """``manifest`` with the format, architecture, observation, actions and provenance filled in."""
    if not isinstance(manifest, Mapping):
        raise BundleError(f"manifest must be a dict, got {type(manifest).__name__}")
    unknown = sorted(set(manifest) - _MANIFEST_KEYS, key=str)
    if unknown:
        raise BundleError(f"manifest: unknown keys {safe_names(unknown)}; allowed: {sorted(_MANIFEST_KEYS)}")
    try:
        full: dict[str, Any] = json.loads(json.dumps(dict(manifest)))  # deep copy; proves JSON-able
    except (TypeError, ValueError) as exc:
        raise BundleError(f"manifest must hold JSON values only (str, int, float, bool, None, lists, "
                          f"dicts): {exc}") from None
    desc = _application(full.get("application"))
    c, h, w = net.obs_shape
    default_channels = default_actions = None
    full["format"] = FORMAT
    full["format_version"] = FORMAT_VERSION
    full["architecture"] = net.spec
    obs = dict(full.get("observation") or {})
    if desc is not None:
        default_actions = list(desc.action_names) or None
        if desc.manifest_names_view:
            spec = _observation_spec(desc, obs.get("name", "maps"))
            obs["name"] = spec.name
            obs.setdefault("channel_names", list(desc.channels(spec)))
        else:
            try:
                spec = desc.view(obs.get("name", "maps"))
            except ValueError:  # validate_manifest reports the name
                spec = desc.view("maps")
            default_channels = list(desc.channels(spec))
    obs.setdefault("channels", c)
    obs.setdefault("height", h)
    obs.setdefault("width", w)
    if default_channels is None or len(default_channels) != c:
        default_channels = [f"channel_{i}" for i in range(c)]
    obs.setdefault("channel_names", default_channels)
    full["observation"] = obs
    if default_actions is None or len(default_actions) != net.num_actions:
        default_actions = [f"action_{i}" for i in range(net.num_actions)]
    full.setdefault("actions", default_actions)
    full.setdefault("environment", {})
    # A metric that was not measured (NaN) is stored as null: strict JSON has no NaN.
    metrics = full.setdefault("metrics", {})
    if isinstance(metrics, dict):
        full["metrics"] = {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                           for k, v in metrics.items()}
    training = dict(full.get("training") or {})
    training.setdefault("code_version", medc_training.__version__)
    if "git_commit" not in training:
        training["git_commit"] = _git_commit()
    full["training"] = training
    return validate_manifest(full)


def manifest_observation(manifest: Mapping[str, Any]) -> str | None:
    """The observation variant a validated manifest's model takes: its ``observation.name``; for
    an application with estimate views (target localization) 'maps' when the manifest predates
    variants; None for another application's manifest without a name (its absolute maps)."""
    name = manifest["observation"].get("name")
    if name is None and _names_view(manifest.get("application")):
        return "maps"
    return None if name is None else str(name)


def manifest_sensing(manifest: Mapping[str, Any]) -> str:
    """The sensing preset a validated target-localization manifest's model was trained under: its
    ``environment.sensing`` (the core records it when it is not the default), 'paper-simple' when
    the manifest names none (every bundle made before the presets).

    Raises:
        BundleError: ``environment.sensing`` is not the name of a preset
        (:data:`medc_training.envs.tl_sensing.SENSING_PRESETS`).
    """
    from medc_training.envs.tl_sensing import DEFAULT_SENSING, SENSING_PRESETS

    name = (manifest.get("environment") or {}).get("sensing", DEFAULT_SENSING)
    if not isinstance(name, str) or name not in SENSING_PRESETS:
        raise BundleError(f"manifest: environment.sensing is {safe_repr(name)}, not one of "
                          f"{', '.join(sorted(SENSING_PRESETS))}")
    return name


def manifest_prior(manifest: Mapping[str, Any]) -> tuple[float, float, int] | None:
    """The background prior (low, high, levels) the team's estimator was trained under, from a
    manifest's ``environment`` (``prior_background_low/high/levels``: a benchmark-world option); None
    when it records none (the sensing model's own).

    Raises:
        BundleError: the manifest records a partial or malformed prior.
    """
    from medc_training.radbench.physics import background_prior

    try:
        return background_prior(dict(manifest.get("environment") or {}))
    except ValueError as e:
        raise BundleError(f"manifest: environment: {e}") from None


def check_sensing(manifest: Mapping[str, Any], sensing: Any, what: str = "this bundle") -> None:
    """Refuse a target-localization bundle trained under another sensing preset than ``sensing``
    (the team's: a preset's name or a model), or whose estimator was trained under a background
    prior (:func:`manifest_prior`) other than the team model's. Raises BundleError naming both;
    ``what`` names the bundle in it."""
    from medc_training.envs.tl_sensing import parse_sensing

    mine = manifest_sensing(manifest)
    model = parse_sensing(sensing)
    team = model.name
    if mine != team:
        raise BundleError(
            f"{what} was trained under the sensing model {mine!r}, but this team senses with {team!r}; "
            f"use a bundle trained with sensing {team!r} (environment.sensing in its manifest; none "
            f"means 'paper-simple'), or run the team with sensing {mine!r}"
        )
    prior = manifest_prior(manifest)
    if prior is not None and (model.background, model.levels[1]) != (prior[:2], prior[2]):
        raise BundleError(
            f"{what}'s estimator was trained under the background prior {prior[0]:g}-{prior[1]:g} counts/s "
            f"at {prior[2]} levels, but this team's model weighs {model.background[0]:g}-"
            f"{model.background[1]:g} at {model.levels[1]}; run it under its own prior "
            f"(medc-radbench --prior-background {prior[0]:g},{prior[1]:g},{prior[2]})"
        )


def check_world(manifest: Mapping[str, Any], world: str = "grid", allow: bool = False,
                what: str = "this bundle") -> None:
    """Refuse a bundle trained in another environment than the one it is about to run in: the
    ``world`` (``medc_training.envs.WORLDS``) at the nominal sensor model of its sensing preset.
    Refused: a manifest whose ``environment.world`` is another (none means 'grid') or that names
    any of :data:`medc_training.radbench.world.OFF_NOMINAL_OPTIONS` (domain randomisation,
    ``walls_min``, ``snr_max``). The BundleError names the world and the options (key=value) and says
    how to run it anyway; ``what`` names the bundle in it. ``allow``: check nothing."""
    if allow:
        return
    from medc_training.radbench.world import OFF_NOMINAL_OPTIONS

    env = manifest.get("environment") or {}
    mine = env.get("world", "grid")
    options = [f"{key}={safe_repr(env[key])}" for key in OFF_NOMINAL_OPTIONS if key in env]
    if mine == world and not options:
        return
    given = f" with {', '.join(options)}" if options else ""
    raise BundleError(
        f"{what} was trained in the {safe_repr(mine)} world{given}, but it is about to run in the "
        f"{world!r} world at the nominal sensor model of its sensing preset, where it was never "
        f"measured; use a bundle trained there (environment.world in its manifest, none means "
        f"'grid'; no domain randomisation, walls_min or snr_max), or run it anyway with allow_other_world "
        f"true (a medc-launch config key and an agent node parameter)"
    )


def _observation_spec(desc: Application, name: Any):
    """The view ``name`` of application ``desc``; BundleError when it takes no such view."""
    try:
        return desc.view(name)
    except ValueError:  # its message holds the name: do not echo it
        raise BundleError(f"manifest: observation.name is not a view {desc.name} takes "
                          f"({', '.join(desc.views)})") from None


def _git_commit() -> str | None:
    """HEAD of the repository this code runs from, or None when it is not a git checkout."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent,
            capture_output=True, text=True, timeout=5, check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    commit = out.stdout.strip()
    return commit if out.returncode == 0 and len(commit) == 40 else None


def _is_scalar(value: Any) -> bool:
    if isinstance(value, float):
        return math.isfinite(value)
    return value is None or isinstance(value, str | int | bool)


def _check_int(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise BundleError(f"manifest: {what} must be a positive integer, got {safe_repr(value)}")
    return value


def _check_names(value: Any, count: int, what: str) -> None:
    if not isinstance(value, list) or not all(isinstance(n, str) and n for n in value):
        raise BundleError(f"manifest: {what} must be a list of non-empty strings")
    if len(value) != count:
        raise BundleError(f"manifest: {what} lists {len(value)} names but the network has {count}")
    if len(set(value)) != len(value):
        raise BundleError(f"manifest: {what} has duplicate names")


def validate_manifest(manifest: Any) -> dict[str, Any]:
    """Check a complete manifest (as stored in a bundle); return it with a normalised architecture.

    Cross-checks the claims against each other: the observation shape and the action count must
    be the architecture's, a ``grid`` environment attribute must match the observation's size, and
    the application must be one this code knows.
    """
    _check_keys(manifest)
    _check_format(manifest)
    app = _check_application(manifest)
    _check_sections(manifest)
    try:
        spec = validate_spec(manifest["architecture"])
    except SpecError as exc:
        raise BundleError(f"manifest: invalid architecture: {exc}") from None
    shape = _check_shapes(manifest, spec)
    _check_scenario_size(manifest["environment"])
    _check_view(app, manifest["observation"], shape, manifest["environment"].get("grid"))
    out = dict(manifest)
    out["architecture"] = spec
    return out


def _check_keys(manifest: Any) -> None:
    if not isinstance(manifest, dict):
        raise BundleError(f"manifest must be a JSON object, got {type(manifest).__name__}")
    unknown = sorted(set(manifest) - _MANIFEST_KEYS, key=str)
    if unknown:
        raise BundleError(f"manifest: unknown keys {safe_names(unknown)}; allowed: {sorted(_MANIFEST_KEYS)}")
    missing = sorted(_MANIFEST_KEYS - {"description"} - set(manifest))
    if missing:
        raise BundleError(f"manifest: missing keys {missing}")


def _check_format(manifest: dict[str, Any]) -> None:
    if manifest["format"] != FORMAT:
        raise BundleError(f"manifest: format is {safe_repr(manifest['format'])}, expected {FORMAT!r}")
    version = manifest["format_version"]
    if isinstance(version, bool) or not isinstance(version, int):
        raise BundleError(f"manifest: format_version must be an integer, got {safe_repr(version)}")
    if version != FORMAT_VERSION:
        newer = " (written by a newer medc_training; upgrade to load it)" if version > FORMAT_VERSION else ""
        raise BundleError(f"manifest: format_version {version} is not supported, expected "
                          f"{FORMAT_VERSION}{newer}")


def _check_application(manifest: dict[str, Any]) -> str:
    app = manifest["application"]
    if _application(app) is None:
        raise BundleError(f"manifest: unknown application {safe_repr(app)}; known: "
                          f"{', '.join(APPLICATIONS)}")
    if "description" in manifest and not isinstance(manifest["description"], str):
        raise BundleError("manifest: description must be a string")
    return app


def _check_sections(manifest: dict[str, Any]) -> None:
    """environment, training and metrics are objects; environment attributes (they feed the
    registry's distance D_m) and metrics are flat scalars."""
    for section in ("environment", "training", "metrics"):
        value = manifest[section]
        if not isinstance(value, dict):
            raise BundleError(f"manifest: {section} must be an object, got {type(value).__name__}")
        if section == "training":
            continue
        for key, item in value.items():
            if _is_scalar(item):
                continue
            if section == "environment":
                raise BundleError(f"manifest: environment.{safe_repr(key)[1:-1]} must be a finite number, "
                                  f"bool or string, got {safe_repr(item)}")
            raise BundleError(f"manifest: metrics.{safe_repr(key)[1:-1]} must be a finite number, bool, "
                              "string or null")


def _check_scenario_size(env: dict[str, Any]) -> None:
    """``environment.grid`` and ``environment.agents``, when numbers, are whole and within
    ``MAX_BUNDLE_GRID`` / ``MAX_BUNDLE_AGENTS``: checked before anything is sized from them."""
    for key, most in (("grid", MAX_BUNDLE_GRID), ("agents", MAX_BUNDLE_AGENTS)):
        value = env.get(key)
        if isinstance(value, bool) or not isinstance(value, int | float):
            continue
        if value != int(value) or not 1 <= value <= most:
            raise BundleError(f"manifest: environment.{key} is {safe_repr(value)}, but a bundle may name "
                              f"a whole number from 1 to {most} (MAX_BUNDLE_{key.upper()}: what an agent "
                              f"node can be asked to allocate for)")


def _check_shapes(manifest: dict[str, Any], spec: dict[str, Any]) -> tuple[int, int, int]:
    """The observation's (channels, height, width): the architecture's input; channel and action
    names as many as the network has."""
    obs = manifest["observation"]
    keys = {"channels", "height", "width", "channel_names"}
    if not isinstance(obs, dict) or not keys <= set(obs) <= keys | {"name"}:
        raise BundleError("manifest: observation must be {channels, height, width, channel_names[, name]}")
    shape = tuple(_check_int(obs[k], f"observation.{k}") for k in ("channels", "height", "width"))
    net_shape = (spec["input"]["channels"], spec["input"]["height"], spec["input"]["width"])
    if shape != net_shape:
        raise BundleError(f"manifest: observation shape {list(shape)} does not match the architecture's "
                          f"input {list(net_shape)}")
    _check_names(obs["channel_names"], shape[0], "observation.channel_names")
    _check_names(manifest["actions"], spec["layers"][-1]["num_actions"], "actions")
    return shape


def _check_view(app: str, obs: dict[str, Any], shape: tuple[int, int, int], grid: Any) -> None:
    """The observation's name (its view), channel names and size agree with the application and
    the environment's grid."""
    name = obs.get("name")
    has_grid = isinstance(grid, int) and not isinstance(grid, bool)
    if name is None:
        if grid is not None and (grid != shape[1] or grid != shape[2]):
            raise BundleError(f"manifest: environment.grid is {safe_repr(grid)} but the observation is "
                              f"{shape[1]}x{shape[2]}")
        return
    desc = APPLICATIONS[app]
    spec = _observation_spec(desc, name)
    channels = list(desc.channels(spec))
    if desc.manifest_names_view and list(obs["channel_names"]) != channels:
        raise BundleError(f"manifest: observation {spec.name} has channels {channels}, "
                          "but channel_names differ")
    side = spec.side(grid if has_grid else shape[1])
    if (shape[1], shape[2]) != (side, side):
        grid_says = f"environment.grid is {safe_repr(grid)} but the observation is " if has_grid else ""
        raise BundleError(f"manifest: {grid_says}{shape[1]}x{shape[2]} with {shape[0]} channels; "
                          f"observation {safe_repr(spec.name)} is {side}x{side} here")
