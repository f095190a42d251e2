"""``medc-inspect BUNDLE``: verify a policy bundle and print its manifest.

Exit status: 0 for a valid bundle, 1 for a file that is not a valid bundle (the reason goes to
stderr), 2 for bad command-line usage.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from medc_training.bundle import BundleError, load_bundle, read_manifest


def _layer_text(layer: dict[str, Any]) -> str:
    kind = layer["type"]
    if kind == "conv2d":
        return (f"conv2d {layer['kernel_size']}x{layer['kernel_size']} -> {layer['out_channels']}"
                f" (stride {layer['stride']}, pad {layer['padding']})")
    if kind == "maxpool2d":
        ceil = ", ceil" if layer["ceil_mode"] else ""
        return f"maxpool2d {layer['kernel_size']}x{layer['kernel_size']} (stride {layer['stride']}{ceil})"
    if kind == "linear":
        return f"linear -> {layer['out_features']}"
    if kind == "heads":
        return f"heads: policy {layer['num_actions']}, value 1"
    return kind


def _mapping_lines(title: str, mapping: dict[str, Any]) -> list[str]:
    if not mapping:
        return [f"{title + ':':<14}(none)"]
    lines = [f"{title}:"]
    width = max(len(k) for k in mapping)
    lines += [f"  {k:<{width}}  {json.dumps(v) if not isinstance(v, str) else v}" for k, v in mapping.items()]
    return lines


def format_manifest(manifest: dict[str, Any], sha256: str | None = None, parameters: int | None = None,
                    size: int | None = None) -> str:
    """A readable multi-line summary of a validated manifest."""
    obs = manifest["observation"]
    arch = manifest["architecture"]
    lines = [
        f"{'application:':<14}{manifest['application']}",
        f"{'format:':<14}{manifest['format']} v{manifest['format_version']}",
    ]
    if manifest.get("description"):
        lines.append(f"{'description:':<14}{manifest['description']}")
    if sha256:
        lines.append(f"{'sha256:':<14}{sha256}")
    if size is not None:
        lines.append(f"{'size:':<14}{size} bytes")
    lines += _mapping_lines("environment", manifest["environment"])
    lines.append(f"{'observation:':<14}{obs['channels']} x {obs['height']} x {obs['width']} "
                 f"({', '.join(obs['channel_names'])})")
    lines.append(f"{'actions:':<14}{len(manifest['actions'])} ({', '.join(manifest['actions'])})")
    params = f", {parameters:,} parameters" if parameters is not None else ""
    lines.append(f"architecture: {arch['name']} ({len(arch['layers'])} layers{params})")
    lines += [f"  {i:>2}  {_layer_text(layer)}" for i, layer in enumerate(arch["layers"])]
    lines += _mapping_lines("training", manifest["training"])
    lines += _mapping_lines("metrics", manifest["metrics"])
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``medc-inspect`` console script."""
    parser = argparse.ArgumentParser(
        prog="medc-inspect",
        description="Verify a MEDC policy bundle (.safetensors) and print its manifest. Exits 1 with the "
                    "reason when the file is not a valid bundle.",
    )
    parser.add_argument("bundle", help="path to the bundle file")
    parser.add_argument("--json", action="store_true", help="print the raw manifest as JSON")
    parser.add_argument("--manifest-only", action="store_true",
                        help="check the header and manifest only, without decoding the weights")
    args = parser.parse_args(argv)
    try:
        if args.manifest_only:
            manifest = read_manifest(args.bundle)
            sha256 = parameters = None
        else:
            bundle = load_bundle(args.bundle)
            manifest, sha256 = bundle.manifest, bundle.sha256
            parameters = sum(p.numel() for p in bundle.net.parameters())
    except BundleError as exc:
        print(f"medc-inspect: invalid bundle: {exc}", file=sys.stderr)
        return 1
    text = (json.dumps(manifest, indent=2, sort_keys=True) if args.json
            else format_manifest(manifest, sha256, parameters, Path(args.bundle).stat().st_size))
    try:
        print(text)
        sys.stdout.flush()
    except BrokenPipeError:
        # `medc-inspect B | head` closing the pipe early is not an error of the bundle.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    return 0


if __name__ == "__main__":
    sys.exit(main())
