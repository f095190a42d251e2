"""``medc-inspect BUNDLE``: verify a policy bundle and print its manifest.

``medc-inspect --export onnx|torchscript BUNDLE OUT``: verify it as an agent does (the timed dry
run included: a bundle the agents refuse is refused with the same reason), write its network to OUT
and its observation/action contract to ``OUT.json`` (medc_training.bundle.export), for onboard
computers. OUT is never the bundle itself; an existing OUT or OUT.json (a link included) is
replaced only with ``--overwrite``, and a link is replaced, never written through.

Exit status: 0 for a valid bundle, 1 for a file that is not a valid bundle (the reason goes to
stderr), 2 for bad command-line usage. Whatever the file holds, it never ends in a traceback, and
every string from the manifest is printed sanitised: control characters (ANSI escapes included),
format characters (bidirectional overrides) and anything unprintable appear as ``\\xNN`` /
``\\uNNNN`` escapes, never raw.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import unicodedata
from pathlib import Path
from typing import Any

from medc_training.bundle import BundleError, load_bundle, read_manifest
from medc_training.outfiles import OutputError


def clean(value: Any) -> str:
    """``value`` as text safe for a terminal: every control, format, surrogate, private-use,
    unassigned or separator character (other than the space) shown as an escape."""
    text = value if isinstance(value, str) else json.dumps(value)
    out = []
    for ch in text:
        if ch == " " or unicodedata.category(ch)[0] not in "CZ":
            out.append(ch)
        else:
            code = ord(ch)
            out.append(f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}" if code < 0x10000
                       else f"\\U{code:08x}")
    return "".join(out)


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
    keys = {k: clean(k) for k in mapping}
    width = max(len(k) for k in keys.values())
    lines += [f"  {keys[k]:<{width}}  {clean(v)}" for k, v in mapping.items()]
    return lines


def format_manifest(manifest: dict[str, Any], sha256: str | None = None, parameters: int | None = None,
                    size: int | None = None) -> str:
    """A readable multi-line summary of a validated manifest."""
    obs = manifest["observation"]
    arch = manifest["architecture"]
    lines = [
        f"{'application:':<14}{clean(manifest['application'])}",
        f"{'format:':<14}{clean(manifest['format'])} v{manifest['format_version']}",
    ]
    if manifest.get("description"):
        lines.append(f"{'description:':<14}{clean(manifest['description'])}")
    if sha256:
        lines.append(f"{'sha256:':<14}{sha256}")
    if size is not None:
        lines.append(f"{'size:':<14}{size} bytes")
    lines += _mapping_lines("environment", manifest["environment"])
    lines.append(f"{'observation:':<14}{obs['channels']} x {obs['height']} x {obs['width']} "
                 f"({', '.join(clean(n) for n in obs['channel_names'])})")
    actions = ", ".join(clean(a) for a in manifest["actions"])
    lines.append(f"{'actions:':<14}{len(manifest['actions'])} ({actions})")
    params = f", {parameters:,} parameters" if parameters is not None else ""
    lines.append(f"architecture: {clean(arch['name'])} ({len(arch['layers'])} layers{params})")
    lines += [f"  {i:>2}  {_layer_text(layer)}" for i, layer in enumerate(arch["layers"])]
    lines += _mapping_lines("training", manifest["training"])
    lines += _mapping_lines("metrics", manifest["metrics"])
    return "\n".join(lines)


def _export(bundle: str, out: str, fmt: str, overwrite: bool = False) -> int:
    from medc_training.bundle.export import export_bundle

    try:
        model, side = export_bundle(bundle, out, fmt, overwrite=overwrite)
    except ImportError as exc:
        print(f"medc-inspect: --export {fmt} needs {exc.name or exc}: pip install -r requirements.txt",
              file=sys.stderr)
        return 1
    except Exception as exc:  # BundleError, or anything at all: a reason, never a traceback
        reason = str(exc) if isinstance(exc, BundleError | OutputError) else (
            f"{clean(str(bundle))}: cannot be exported ({type(exc).__name__}: {exc})")
        print(f"medc-inspect: {clean(reason)}", file=sys.stderr)
        return 1
    print(f"wrote {clean(str(model))} ({fmt}) and {clean(str(side))} (observation/action contract)")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``medc-inspect`` console script."""
    from ..console import HelpFormatter

    parser = argparse.ArgumentParser(
        prog="medc-inspect",
        formatter_class=HelpFormatter,
        description="Verify a MEDC policy bundle (.safetensors) and print its manifest. Exits 1 with the "
                    "reason when the file is not a valid bundle.",
    )
    parser.add_argument("bundle", help="path to the bundle file")
    parser.add_argument("out", nargs="?",
                        help="with --export: the model file to write (OUT.json: its contract)")
    parser.add_argument("--export", choices=["onnx", "torchscript"],
                        help="write the network as ONNX or TorchScript to OUT, its contract to OUT.json")
    parser.add_argument("--overwrite", action="store_true",
                        help="with --export: replace OUT and OUT.json if they exist (a link is replaced, "
                             "never written through)")
    parser.add_argument("--json", action="store_true", help="print the raw manifest as JSON")
    parser.add_argument("--manifest-only", action="store_true",
                        help="check the header and manifest only, without decoding the weights")
    args = parser.parse_args(argv)
    if args.export and not args.out:
        parser.error("--export needs OUT, the model file to write")
    if args.overwrite and not args.export:
        parser.error("--overwrite is only used with --export onnx|torchscript")
    if args.out and not args.export:
        parser.error("OUT is only used with --export onnx|torchscript")
    for stream in (sys.stdout, sys.stderr):  # a terminal that is not UTF-8 gets escapes, not a crash
        if hasattr(stream, "reconfigure"):
            stream.reconfigure(errors="backslashreplace")
    if args.export:
        return _export(args.bundle, args.out, args.export, args.overwrite)
    try:
        if args.manifest_only:
            manifest = read_manifest(args.bundle)
            sha256 = parameters = None
        else:
            bundle = load_bundle(args.bundle)
            manifest, sha256 = bundle.manifest, bundle.sha256
            parameters = sum(p.numel() for p in bundle.net.parameters())
        # --json: ensure_ascii escapes every non-ASCII and control character.
        text = (json.dumps(manifest, indent=2, sort_keys=True) if args.json
                else format_manifest(manifest, sha256, parameters, Path(args.bundle).stat().st_size))
    except Exception as exc:  # BundleError, or anything at all: a reason, never a traceback
        reason = str(exc) if isinstance(exc, BundleError) else (
            f"{clean(str(args.bundle))}: cannot be loaded ({type(exc).__name__})")
        print(f"medc-inspect: invalid bundle: {clean(reason)}", file=sys.stderr)
        return 1
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
