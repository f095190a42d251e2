"""Policy bundles: one safetensors file holding a trained policy and its JSON manifest.

A bundle is untrusted data: its header is checked before any tensor is decoded, nothing is
unpickled, and the network is rebuilt from the manifest's declarative spec (``BundleError`` says
what is wrong). Split by job, every name importable from here: ``manifest`` (the schema),
``fileformat`` (the hardened reader, atomic writes), ``policy`` (``PolicyBundle``, saving, the
loaders), ``dryrun`` (the timed dry run), ``checkpoint`` (training checkpoints), ``ensemble`` (several
bundles as one policy). The manifest and what loading checks: docs/bundles.md, "Bundles".
"""

from medc_training.bundle.checkpoint import load_state, save_state
from medc_training.bundle.dryrun import dry_run_observations, flush_denormals, flush_subnormal
from medc_training.bundle.ensemble import ensemble, load_ensemble
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
    check_world,
    complete_manifest,
    manifest_observation,
    manifest_prior,
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
    "bundle_digest", "check_sensing", "check_world", "complete_manifest", "dry_run_observations",
    "dry_run_seconds",
    "ensemble", "flush_denormals", "flush_subnormal", "json_depth",
    "load_bundle", "load_ensemble", "load_state", "load_untrusted", "manifest_observation",
    "manifest_prior", "manifest_sensing",
    "parse_json", "printable", "read_manifest", "save_bundle", "save_state", "validate_manifest",
]
