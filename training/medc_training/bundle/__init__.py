"""Policy bundles: one safetensors file holding a trained policy and its JSON manifest.

A bundle is a plain safetensors file (readable by any safetensors tool). Its tensors are the
actor-critic's parameters (float32, named as in ``medc_training.nets``); its metadata holds one
entry, ``"medc.manifest"``, a JSON object:

.. code-block:: text

    format            "medc-policy-bundle"
    format_version    1
    application       the name of an application of medc_training.envs.APPLICATIONS
    description       optional free text (what the registry shows)
    environment       {attribute: number | bool | string}, e.g. {"agents": 3, "walls": 2, "grid": 30}
    observation       {"channels": C, "height": H, "width": W, "channel_names": [C names],
                       "name": variant}; "name" is the observation variant the model takes
                       (target localization: "maps", "egoR", each with "+estimate", "+posterior"
                       or "+estimate+posterior", see medc_training.envs.tl_observation); a bundle
                       without it takes "maps"
    actions           [A action names], e.g. ["N", "NE", "E", "SE", "S", "SW", "W", "NW"]
    architecture      the declarative network spec (medc_training.nets), input C x H x W, A actions
    training          {"method", "steps", "seed", "code_version", "git_commit", ...}
    metrics           {name: number | string | bool | null}, e.g. {"mean_episode_length": 23.4}

One file means one IPFS CID: the registry stores and verifies exactly these bytes.

Loading treats a bundle as untrusted data: the header is parsed and checked here before any tensor
is decoded; nothing is unpickled and no code from the file runs; the network is rebuilt from the
declarative spec and every stored tensor is checked against the shapes that spec implies. Anything
wrong raises ``BundleError`` with a message saying what is wrong.

Training checkpoints (``save_state`` / ``load_state``) reuse the same container for arbitrary nested
state (model and optimizer state dicts, RNG states, counters) without pickle: tensors are stored by
flattened name, everything else as JSON in the metadata.

The package is split by job; every name is importable from ``medc_training.bundle``:

* :mod:`~medc_training.bundle.manifest`: the manifest schema, completed on save and validated on load;
* :mod:`~medc_training.bundle.fileformat`: the hardened safetensors/JSON reader and atomic writes;
* :mod:`~medc_training.bundle.policy`: ``PolicyBundle``, saving and the loaders;
* :mod:`~medc_training.bundle.dryrun`: what a policy costs on this machine (the timed dry run);
* :mod:`~medc_training.bundle.checkpoint`: training checkpoints.
"""

from medc_training.bundle.checkpoint import load_state, save_state
from medc_training.bundle.dryrun import dry_run_observations, flush_denormals, flush_subnormal
from medc_training.bundle.fileformat import (
    MANIFEST_KEY,
    MAX_HEADER_BYTES,
    MAX_JSON_DEPTH,
    MAX_MANIFEST_CHARS,
    MAX_NUMBER_CHARS,
    MAX_STRING_CHARS,
    BundleError,
    json_depth,
    parse_json,
)
from medc_training.bundle.manifest import (
    FORMAT,
    FORMAT_VERSION,
    KNOWN_APPLICATIONS,
    MAX_BUNDLE_AGENTS,
    MAX_BUNDLE_GRID,
    check_sensing,
    complete_manifest,
    manifest_observation,
    manifest_sensing,
    validate_manifest,
)
from medc_training.bundle.policy import (
    MAX_FORWARD_SECONDS,
    PolicyBundle,
    bundle_bytes,
    bundle_digest,
    dry_run_seconds,
    load_bundle,
    load_untrusted,
    read_manifest,
    save_bundle,
)
from medc_training.untrusted import MAX_BUNDLE_BYTES, printable

__all__ = [
    "FORMAT", "FORMAT_VERSION", "KNOWN_APPLICATIONS", "MANIFEST_KEY", "MAX_BUNDLE_AGENTS", "MAX_BUNDLE_BYTES",
    "MAX_BUNDLE_GRID",
    "MAX_FORWARD_SECONDS", "MAX_HEADER_BYTES", "MAX_JSON_DEPTH", "MAX_MANIFEST_CHARS",
    "MAX_NUMBER_CHARS", "MAX_STRING_CHARS", "BundleError", "PolicyBundle", "bundle_bytes",
    "bundle_digest", "check_sensing", "complete_manifest", "dry_run_observations", "dry_run_seconds",
    "flush_denormals", "flush_subnormal", "json_depth",
    "load_bundle", "load_state", "load_untrusted", "manifest_observation", "manifest_sensing",
    "parse_json", "printable", "read_manifest", "save_bundle", "save_state", "validate_manifest",
]
