"""Hostile bundles built here, in several sizes and shapes, end in a BundleError that says
what is wrong and never echoes the file; the same refusal from the agent's and the bridge's
shared vetting (load_untrusted) and from medc-inspect; nothing else ever escapes."""

from __future__ import annotations

import copy
import json
import os
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from bundle_forge import bomb_spec, conv, forge, nested, raw_header, spec_parts, valid_parts, with_raw_section
from medc_training.bundle import (
    MAX_FORWARD_SECONDS,
    MAX_JSON_DEPTH,
    MAX_MANIFEST_CHARS,
    MAX_STRING_CHARS,
    BundleError,
    json_depth,
    load_bundle,
    load_untrusted,
    read_manifest,
)
from medc_training.bundle import policy as bundle_mod
from medc_training.cli.inspect import main as inspect_main
from medc_training.nets import (
    MAX_ACTIVATION_BYTES,
    MAX_OPERATIONS,
    SpecError,
    architecture_cost,
    architecture_spec,
    validate_spec,
)


def refused(data: bytes, message: str) -> str:
    """Every loader refuses ``data`` with ``message`` in a BundleError; returns the message."""
    for load in (load_bundle, read_manifest, load_untrusted):
        with pytest.raises(BundleError, match=message) as info:
            load(data)
    return str(info.value)


# --- 1. deeply nested and malformed manifests ------------------------------------------------

@pytest.mark.parametrize("depth", [MAX_JSON_DEPTH + 1, 2_000, 100_000])
@pytest.mark.parametrize("kind", ["list", "object"])
@pytest.mark.parametrize("section", ["training", "metrics", "environment", "description", "architecture"])
def test_deep_nesting_anywhere_in_the_manifest(parts, depth, kind, section) -> None:
    tensors, manifest = parts
    text = with_raw_section(manifest, section, nested(depth, kind))
    # As deep as fits the manifest size limit: said so; deeper: over the size limit, said so.
    refused(forge(tensors, None, raw_manifest=text),
            f"manifest nests deeper than {MAX_JSON_DEPTH} levels" if len(text) <= MAX_MANIFEST_CHARS
            else f"manifest is over the {MAX_MANIFEST_CHARS} character limit")


@pytest.mark.parametrize("depth", [2_000, 300_000])
def test_deep_manifest_itself_and_deep_header(parts, depth) -> None:
    tensors, _ = parts
    refused(forge(tensors, None, raw_manifest=nested(depth)), "manifest nests deeper|manifest is over the")
    header = '{"__metadata__": {"medc.manifest": "{}"}, "x": ' + nested(min(depth, 100_000), "object") + "}"
    refused(raw_header(header.encode()), "header nests deeper")


def test_nesting_at_the_limit_is_parsed(parts) -> None:
    tensors, manifest = parts
    # manifest -> training -> 14 more levels: exactly MAX_JSON_DEPTH; accepted (training is free-form).
    text = with_raw_section(manifest, "training", nested(MAX_JSON_DEPTH - 2, "object"))
    load_bundle(forge(tensors, None, raw_manifest=text))


def test_depth_scan_ignores_brackets_inside_strings() -> None:
    assert json_depth('{"a": "[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[\\"[[["}') == 1
    assert json_depth(nested(40)) == 40
    assert json_depth("") == 0


def test_a_raised_recursion_limit_cannot_turn_depth_into_a_crash(parts, tmp_path) -> None:
    """The bridge runs with web3's raised recursion limit: 100,000 levels used to segfault it."""
    tensors, _ = parts
    deep_manifest = tmp_path / "deep_manifest.safetensors"  # as deep as the manifest size limit allows
    deep_manifest.write_bytes(forge(tensors, None, raw_manifest=nested(MAX_MANIFEST_CHARS // 2)))
    deep_header = tmp_path / "deep_header.safetensors"  # as deep as the header size limit allows
    deep_header.write_bytes(raw_header(('{"__metadata__": {"medc.manifest": "{}"}, "x": '
                                        + nested(500_000) + "}").encode()))
    code = textwrap.dedent(f"""
        import sys
        sys.setrecursionlimit(10**6)
        from medc_training.bundle import BundleError, load_bundle
        for path in ({str(deep_manifest)!r}, {str(deep_header)!r}):
            try:
                load_bundle(path)
            except BundleError as exc:
                print("refused:", exc)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, (out.returncode, out.stderr[-2000:])
    assert "manifest nests deeper than" in out.stdout and "header nests deeper than" in out.stdout


@pytest.mark.parametrize(("edit", "message"), [
    (lambda m: m.update(description="x" * (MAX_STRING_CHARS + 1)), "string of more than"),
    (lambda m: m["training"].update({"k" * (MAX_STRING_CHARS + 1): 1}), "string of more than"),
    (lambda m: m.update(description="padding " * (MAX_MANIFEST_CHARS // 8)), "over the 65536 character"),
    (lambda m: m["training"].update(huge=[0] * (MAX_MANIFEST_CHARS // 2)), "over the 65536 character"),
])
def test_oversized_manifests(parts, edit, message) -> None:
    tensors, manifest = parts
    manifest = copy.deepcopy(manifest)
    edit(manifest)
    refused(forge(tensors, manifest), message)


@pytest.mark.parametrize("where", ["description", "training", "environment", "actions", "key"])
def test_lone_surrogates_are_invalid_unicode(parts, where) -> None:
    tensors, manifest = parts
    manifest = copy.deepcopy(manifest)
    bad = "ok\ud800"
    if where == "description":
        manifest["description"] = bad
    elif where == "training":
        manifest["training"]["note"] = ["x", {"deep": "\udfff"}]
    elif where == "environment":
        manifest["environment"]["terrain"] = bad
    elif where == "actions":
        manifest["actions"][3] = bad
    else:
        manifest["metrics"][bad] = 1.0
    text = json.dumps(manifest)  # ensure_ascii: the surrogate travels as a \ud800 escape
    assert "\\ud800" in text or "\\udfff" in text
    refused(forge(tensors, None, raw_manifest=text), "invalid Unicode")


@pytest.mark.parametrize(("literal", "message"), [
    ("1" * 5000, "a number of more than 40 characters"),
    ("1e400", "a number too large for a float"),
    ("-1e999", "a number too large for a float"),
])
def test_number_literals_out_of_range(parts, literal, message) -> None:
    tensors, manifest = parts
    text = with_raw_section(manifest, "training", '{"x": ' + literal + "}")
    refused(forge(tensors, None, raw_manifest=text), message)


@pytest.mark.parametrize(("edit", "message"), [
    (lambda m: m.update(format=["medc"]), "format is a list"),
    (lambda m: m.update(application={"a": 1}), "unknown application an object"),
    (lambda m: m.update(format_version=1.5), "format_version must be an integer, got 1.5"),
    (lambda m: m["observation"].update(height="10"), "observation.height must be a positive integer"),
    (lambda m: m.update(actions="NESW"), "actions must be a list"),
    (lambda m: m["architecture"].update(layers={"0": {"type": "relu"}}), "'layers' must be a non-empty list"),
    (lambda m: m["architecture"]["layers"][0].update(kernel_size=[5]),
     "'kernel_size' must be an integer, got a list"),
    (lambda m: m.update(training=[1]), "training must be an object"),
])
def test_wrong_types_are_refused_without_tracebacks(parts, edit, message) -> None:
    tensors, manifest = parts
    manifest = copy.deepcopy(manifest)
    edit(manifest)
    refused(forge(tensors, manifest), message)


def test_unexpected_loader_failures_are_bundle_errors(parts, monkeypatch) -> None:
    """Even a failure this module does not foresee (here: injected) ends as a BundleError."""
    tensors, manifest = parts
    data = forge(tensors, manifest)

    def boom(*_a, **_k):
        raise RecursionError("maximum recursion depth exceeded")
    monkeypatch.setattr(bundle_mod, "validate_manifest", boom)
    for load in (load_bundle, read_manifest, load_untrusted):
        with pytest.raises(BundleError, match=r"cannot be loaded \(RecursionError in the loader\)"):
            load(data)
    monkeypatch.undo()

    def oom(*_a, **_k):
        raise MemoryError
    monkeypatch.setattr(bundle_mod, "_st_load", oom)
    with pytest.raises(BundleError, match="cannot decode tensors"):
        load_bundle(data)


# --- 2. compute and memory bombs ---------------------------------------------------------------

BOMBS = {
    # the issue's: 13x13 grown by padded 1x1 convolutions, then one large convolution
    "grow-then-large-conv": (bomb_spec(5, 13, 4, 64, [conv(16, 64)]), "operations per observation"),
    "grow-then-wide-conv": (bomb_spec(5, 10, 3, 64, [conv(32, 15, padding=7)]), "operations per observation"),
    "pooling": (bomb_spec(5, 13, 4, 64, [{"type": "maxpool2d", "kernel_size": 64, "stride": 1}]),
                "operations per observation"),
    "cheap-layers": (bomb_spec(1, 13, 8, 64, [{"type": "relu"}] * 240), "operations per observation"),
    "activation-memory": (bomb_spec(5, 13, 4, 64, [conv(40, 1)]), "bytes of activations"),
    "wide-input": ({"name": "wide", "input": {"channels": 64, "height": 512, "width": 512},
                    "layers": [{"type": "maxpool2d", "kernel_size": 64, "stride": 64},
                               {"type": "flatten"}, {"type": "heads", "num_actions": 8}]},
                   "bytes of activations"),
}


@pytest.mark.parametrize("name", list(BOMBS))
def test_bombs_are_refused_from_the_spec_alone(name) -> None:
    spec, message = BOMBS[name]
    with pytest.raises(SpecError, match=message):
        validate_spec(spec)
    cost = architecture_cost(validate_spec_unchecked(spec))
    assert cost.operations > MAX_OPERATIONS or cost.peak_activation_bytes > MAX_ACTIVATION_BYTES
    tensors, manifest = spec_parts(spec)
    assert sum(t.numel() for t in tensors.values()) < 200_000  # small files: size limits do not help
    refused(forge(tensors, manifest), f"invalid architecture: .*{message}")


def validate_spec_unchecked(spec):
    """The spec with defaults filled in, without the caps (to measure a bomb)."""
    from medc_training.nets import _normalise_layer

    return {**spec, "layers": [_normalise_layer(raw, i) for i, raw in enumerate(spec["layers"])]}


SHIPPED_SHAPES = [(5, 10, 10), (5, 13, 13), (5, 30, 30), (5, 64, 64), (8, 61, 61)]


@pytest.mark.parametrize("arch", ["lenet5", "convnet-small", "mlp"])
def test_every_shipped_architecture_is_far_below_the_caps(arch) -> None:
    for shape in SHIPPED_SHAPES:  # the grids the project uses, and agent-centred 61x61x8 windows
        cost = architecture_cost(architecture_spec(arch, shape, 8))
        assert cost.operations * 39 < MAX_OPERATIONS, (arch, shape, cost)
        assert cost.peak_activation_bytes * 64 <= MAX_ACTIVATION_BYTES, (arch, shape, cost)
    # The largest grid target_localization accepts still fits (with less margin).
    cost = architecture_cost(architecture_spec(arch, (5, 256, 256), 8))
    assert cost.operations < MAX_OPERATIONS and cost.peak_activation_bytes < MAX_ACTIVATION_BYTES


def test_shipped_architectures_pass_the_dry_run_limit() -> None:
    torch.manual_seed(0)
    for arch in ("lenet5", "convnet-small", "mlp"):
        tensors, manifest = valid_parts(arch, grid=30)
        load_untrusted(forge(tensors, manifest))


@pytest.mark.timing
def test_a_slow_forward_pass_is_refused(parts) -> None:
    tensors, manifest = parts
    data = forge(tensors, manifest)
    with pytest.raises(BundleError, match=r"takes .* s to evaluate, over the 1e-09 s limit"):
        load_untrusted(data, max_forward_s=1e-09)
    # Remembered by content: the same bytes are refused again without a dry run; under the default
    # limit they pass (the memory is per limit).
    with pytest.raises(BundleError, match=r"over the 1e-09 s limit .*refused before; not checked again"):
        load_untrusted(bytearray(data), max_forward_s=1e-09)
    assert load_untrusted(data, max_forward_s=MAX_FORWARD_SECONDS).sha256 == bundle_mod.bundle_digest(data)


# --- 3. messages never echo the file -------------------------------------------------------------

def _assert_no_echo(message: str, content: bytes, path: Path | None = None) -> None:
    text = message.replace(str(path), "<path>") if path else message
    first8 = content[:8].ljust(8, b"\0")
    for number in (int.from_bytes(first8, "little"), int.from_bytes(first8, "big")):
        assert str(number) not in text, (text, number)
    assert repr(first8) not in text
    raw = content.decode("latin-1")
    for i in range(len(raw) - 3):
        window = raw[i:i + 4]
        if window not in '{"__metadata__": {"medc.manifest"':  # the format's own words
            assert window not in text, (text, window)


SECRETS = {
    "key file": b"SECRET-K3y-9f8a7c6b5d4e3f2a1b0c\n",
    "passwd": b"root:x:0:0:root:/root:/bin/bash\ndaemon:x:1:1:daemon:/usr/sbin\n",
    "short": b"Zq7\x01",
    "small length prefix, JSON with secrets": raw_header(b'{"sk_live_Zq7Wv": {"pass": "hunter2Zq"}}'),
    "small length prefix, duplicate secret keys": raw_header(b'{"tok_Zq7Wv": 1, "tok_Zq7Wv": 2}'),
    "small length prefix, not UTF-8": raw_header(b'{"\xff\xfeZq7Wv": 1}'),
    "small length prefix, broken JSON": raw_header(b'{"Zq7Wv_secret": hunter2}'),
    "small length prefix, metadata secrets": raw_header(b'{"__metadata__": {"Zq7Wv": "hunter2Zq"}}'),
    "truncated header": struct.pack("<Q", 900) + b'{"Zq7Wv_secret": 1}',
}


@pytest.mark.parametrize("name", list(SECRETS))
def test_refusals_never_echo_the_file(tmp_path, name, capsys) -> None:
    content = SECRETS[name]
    path = tmp_path / "secret"
    path.write_bytes(content)
    os.chmod(path, 0o600)
    for load in (load_bundle, read_manifest, load_untrusted):
        with pytest.raises(BundleError) as info:
            load(path)
        _assert_no_echo(str(info.value), content, path)
        with pytest.raises(BundleError) as info:
            load(content)
        _assert_no_echo(str(info.value), content)
    assert inspect_main([str(path)]) == 1
    _assert_no_echo(capsys.readouterr().err, content, path)


def test_names_from_a_manifest_are_sanitised_and_truncated(parts) -> None:
    tensors, manifest = parts
    manifest = copy.deepcopy(manifest)
    manifest["application"] = "\x1b[2J\x1b]0;pwned\x07" + "A" * 500
    message = refused(forge(tensors, manifest), "unknown application")
    assert "\x1b" not in message and "\x07" not in message and "A" * 41 not in message
    manifest = copy.deepcopy(parts[1])
    manifest["environment"]["\x1b[31mred" + "k" * 300] = [1]
    message = refused(forge(tensors, manifest), "must be a finite number")
    assert "\x1b" not in message and "k" * 41 not in message
    big = {f"evil\x1b{i}" + "x" * 100: torch.zeros(1) for i in range(50)}
    message = refused(forge({**tensors, **big}, parts[1]), "unexpected tensors")
    assert "\x1b" not in message and "and 47 more" in message and len(message) < 400


# --- smaller: bounded reads ------------------------------------------------------------------

def test_the_header_is_checked_before_the_rest_is_read(tmp_path, parts, monkeypatch) -> None:
    tensors, manifest = parts
    good = forge(tensors, manifest)
    reads: list[int] = []
    real_pread = os.pread
    monkeypatch.setattr(os, "pread", lambda fd, n, off: reads.append(n) or real_pread(fd, n, off))
    big = 200 << 20  # under MAX_BUNDLE_BYTES: only the header decides
    claim = tmp_path / "claim.safetensors"  # a header length over the limit, then 200 MiB (sparse)
    with claim.open("wb") as fh:
        fh.write(struct.pack("<Q", 2**40))
        fh.truncate(big)
    with pytest.raises(BundleError, match=r"over the .* byte limit"):
        load_bundle(claim)
    assert sum(reads) == 8
    reads.clear()
    trailing = tmp_path / "trailing.safetensors"  # a valid bundle followed by 200 MiB of zeros
    with trailing.open("wb") as fh:
        fh.write(good)
        fh.truncate(big)
    for load in (load_bundle, read_manifest):
        with pytest.raises(BundleError, match="unexpected bytes after the last tensor"):
            load(trailing)
    assert sum(reads) <= 2 * len(good)
    reads.clear()
    ok = tmp_path / "ok.safetensors"
    ok.write_bytes(good)
    n = struct.unpack("<Q", good[:8])[0]
    assert read_manifest(ok) == read_manifest(good)
    assert sum(reads) == 8 + n  # the weights are never read for the manifest
    load_bundle(ok)


# --- smaller: medc-inspect prints nothing raw ------------------------------------------------

def test_inspect_sanitises_every_manifest_string(parts, tmp_path, capsys) -> None:
    tensors, manifest = parts
    manifest = copy.deepcopy(manifest)
    evil = "\x1b[31mred\x1b[0m\x1b]0;title\x07\r\x08\u202e\u2028\x9b"
    manifest["description"] = "desc " + evil
    manifest["environment"]["terrain" + evil] = "rocky" + evil
    manifest["training"]["note" + evil] = evil
    manifest["metrics"]["m" + evil] = "v" + evil
    manifest["observation"].pop("name", None)  # a named observation's channel names are fixed
    manifest["observation"]["channel_names"][0] = "ch" + evil
    manifest["actions"][0] = "N" + evil
    manifest["architecture"]["name"] = "net" + evil[:20]
    path = tmp_path / "evil.safetensors"
    path.write_bytes(forge(tensors, manifest))
    for args in ([str(path)], ["--manifest-only", str(path)], ["--json", str(path)]):
        assert inspect_main(args) == 0
        out = capsys.readouterr().out
        assert "red" in out
        bad = [ch for ch in out if ch != "\n" and (ord(ch) < 0x20 or 0x7f <= ord(ch) < 0xa0
                                                   or ch in "\u202e\u2028")]
        assert bad == [], (args, bad)
    assert inspect_main([str(path)]) == 0
    assert "\\x1b[31mred" in capsys.readouterr().out


def test_inspect_never_crashes(parts, tmp_path) -> None:
    tensors, manifest = parts
    cases = {
        "surrogate": forge(tensors, None, raw_manifest=json.dumps({**manifest, "description": "a\ud800"})),
        "deep": forge(tensors, None, raw_manifest=nested(100_000)),
        "bomb": forge(*spec_parts(BOMBS["grow-then-large-conv"][0])),
    }
    env = {**os.environ, "PYTHONIOENCODING": "ascii"}  # a terminal that cannot print Unicode
    for name, data in cases.items():
        path = tmp_path / f"{name}\x1b[2J.safetensors"
        path.write_bytes(data)
        out = subprocess.run([sys.executable, "-m", "medc_training.cli.inspect", str(path)],
                             capture_output=True, text=True, timeout=120, env=env)
        assert out.returncode == 1, (name, out.stderr[-2000:])
        assert out.stderr.startswith("medc-inspect: invalid bundle:"), (name, out.stderr)
        assert "Traceback" not in out.stderr and "\x1b" not in out.stderr, (name, out.stderr)
