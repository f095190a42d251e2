"""Every way a bundle file can be wrong is rejected with a BundleError that says what is wrong."""

from __future__ import annotations

import copy
import functools
import io
import json
import pickle
import re
import struct

import pytest
import torch
from bundle_forge import forge, raw_header, rewrite_header, valid_parts
from hypothesis import given, settings
from hypothesis import strategies as st
from medc_training.bundle import (
    MANIFEST_KEY,
    MAX_HEADER_BYTES,
    BundleError,
    load_bundle,
    read_manifest,
    save_state,
)


@pytest.fixture(scope="module")
def good(parts) -> bytes:
    tensors, manifest = parts
    data = forge(tensors, manifest)
    load_bundle(data)  # the untampered forgery is valid: every rejection below is the tamper's doing
    return data


def rejected(data: bytes, message: str) -> None:
    """Both loaders refuse ``data`` with ``message`` in the error."""
    with pytest.raises(BundleError, match=message):
        load_bundle(data)
    if "NaN" not in message:  # weights are only decoded by load_bundle
        with pytest.raises(BundleError, match=message):
            read_manifest(data)


# --- the container ---------------------------------------------------------------------------

def test_empty_and_tiny_inputs(good) -> None:
    rejected(b"", "too short")
    rejected(good[:7], "too short")


def test_truncated_anywhere(good) -> None:
    n = struct.unpack("<Q", good[:8])[0]
    rejected(good[:8 + n // 2], "truncated: header needs")
    rejected(good[:8 + n + 100], "truncated: tensors need")
    rejected(good[:-1], "truncated")


def test_trailing_bytes(good) -> None:
    rejected(good + b"\0" * 16, "unexpected bytes after the last tensor")


def test_oversize_header_claim(good) -> None:
    rejected(struct.pack("<Q", MAX_HEADER_BYTES + 1) + good[8:], "over the .* byte limit")
    rejected(struct.pack("<Q", 2**63) + good[8:], "over the .* byte limit")


def test_header_that_is_not_json() -> None:
    rejected(raw_header(b"\xff\xfe not utf-8 "), "header is not valid JSON")
    rejected(raw_header(b"{\"a\": "), "header is not valid JSON")
    rejected(raw_header(b"[1, 2, 3]"), "header must be a JSON object")
    rejected(raw_header(b'{"__metadata__": {"medc.manifest": "NaN"}}'), "manifest is not valid JSON")


def test_duplicate_keys_in_the_header(good) -> None:
    n = struct.unpack("<Q", good[:8])[0]
    text = good[8:8 + n].decode().rstrip()
    dup = text[:-1] + ', "policy.bias": {"dtype": "F32", "shape": [8], "data_offsets": [0, 32]}}'
    rejected(raw_header(dup.encode(), good[8 + n:]), "a key appears twice in one object")


def test_plain_safetensors_file_is_not_a_bundle(parts) -> None:
    from safetensors.torch import save

    rejected(save(parts[0]), "not a MEDC policy bundle")
    rejected(save(parts[0], metadata={"format": "pt"}), "not a MEDC policy bundle")


def test_training_checkpoint_is_not_a_bundle(tmp_path) -> None:
    path = save_state(tmp_path / "ckpt.safetensors", {"step": 3, "w": torch.zeros(2)})
    with pytest.raises(BundleError, match="not a MEDC policy bundle"):
        load_bundle(path)


def test_overlapping_or_gapped_offsets(good) -> None:
    def overlap(header):
        header["policy.bias"]["data_offsets"] = list(header["value.bias"]["data_offsets"])
        header["policy.bias"]["shape"] = [1]
    rejected(rewrite_header(good, overlap), "overlap or gap")

    def lie_about_size(header):
        header["value.bias"]["shape"] = [2]
    rejected(rewrite_header(good, lie_about_size), "does not fit its byte range")


@pytest.mark.parametrize("dtype", ["F64", "I64", "U8", "BF16"])
def test_non_float32_tensors(good, dtype: str) -> None:
    def retype(header):
        header["value.bias"]["dtype"] = dtype
    rejected(rewrite_header(good, retype), f"dtype '{dtype}'; bundles hold F32 only")


def test_a_pickle_is_rejected_without_being_unpickled(tmp_path) -> None:
    marker = tmp_path / "pwned"

    class Exploit:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    payload = pickle.dumps(Exploit())
    rejected(payload, "not a bundle, or corrupted")
    buffer = io.BytesIO()
    torch.save({"policy.weight": torch.zeros(2)}, buffer)  # what a torch.save checkpoint looks like
    rejected(buffer.getvalue(), "not a bundle, or corrupted")
    path = tmp_path / "model.safetensors"
    path.write_bytes(payload)
    with pytest.raises(BundleError):
        load_bundle(path)
    assert not marker.exists()


def test_paths_that_are_not_files(tmp_path) -> None:
    with pytest.raises(BundleError, match="no such file"):
        load_bundle(tmp_path / "missing.safetensors")
    with pytest.raises(BundleError, match=r"directory|not a regular file"):
        load_bundle(tmp_path)


# --- tensors vs architecture -----------------------------------------------------------------

def test_missing_tensor(parts) -> None:
    tensors, manifest = parts
    rejected(forge({k: v for k, v in tensors.items() if k != "trunk.3.weight"}, manifest),
             r"missing tensors \['trunk.3.weight'\]")


def test_extra_tensor(parts) -> None:
    tensors, manifest = parts
    rejected(forge({**tensors, "backdoor.weight": torch.zeros(3)}, manifest),
             r"unexpected tensors \['backdoor.weight'\]")


def test_wrong_tensor_shape(parts) -> None:
    tensors, manifest = parts
    rejected(forge({**tensors, "policy.weight": torch.zeros(9, 84)}, manifest),
             r"'policy.weight' has shape \[9, 84\], the architecture needs \[8, 84\]")
    rejected(forge({**tensors, "trunk.0.weight": torch.zeros(6, 5, 3, 3)}, manifest),
             "'trunk.0.weight' has shape")


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_non_finite_weights(parts, bad: float) -> None:
    tensors, manifest = parts
    poisoned = tensors["trunk.7.weight"].clone()
    poisoned[3, 5] = bad
    rejected(forge({**tensors, "trunk.7.weight": poisoned}, manifest),
             "'trunk.7.weight' contains NaN or infinite values")


# --- the manifest ----------------------------------------------------------------------------

def edited(parts, edit) -> bytes:
    tensors, manifest = parts
    manifest = copy.deepcopy(manifest)
    edit(manifest)
    return forge(tensors, manifest)


def test_unknown_layer_type(parts) -> None:
    def inject(m):
        m["architecture"]["layers"][1] = {"type": "python", "source": "__import__('os').system('x')"}
    rejected(edited(parts, inject), "invalid architecture: layer 1: unknown layer type 'python'")


def test_architecture_that_does_not_fit_together(parts) -> None:
    def drop_flatten(m):
        del m["architecture"]["layers"][6]
    rejected(edited(parts, drop_flatten), "invalid architecture: .*flatten")

    def resize(m):
        m["architecture"]["layers"][7]["out_features"] = 64
    rejected(edited(parts, resize), r"'trunk.7.weight' has shape \[120, 1024\]|has shape")


def test_observation_shape_that_lies(parts) -> None:
    def claim_grid_30(m):
        m["observation"]["height"] = m["observation"]["width"] = 30
    rejected(edited(parts, claim_grid_30), r"observation shape \[5, 30, 30\] does not match the architecture")

    def claim_4_channels(m):
        m["observation"]["channels"] = 4
        m["observation"]["channel_names"] = m["observation"]["channel_names"][:4]
    rejected(edited(parts, claim_4_channels), "does not match the architecture's input")

    def env_grid(m):
        m["environment"]["grid"] = 30
    rejected(edited(parts, env_grid), "environment.grid is 30 but the observation is 10x10")

    def names(m):
        m["observation"]["channel_names"] = ["a", "b"]
    rejected(edited(parts, names), "channel_names lists 2 names but the network has 5")


def test_action_count_that_lies(parts) -> None:
    def nine(m):
        m["actions"] = [*m["actions"], "UP"]
    rejected(edited(parts, nine), "actions lists 9 names but the network has 8")

    def duplicate(m):
        m["actions"][1] = "N"
    rejected(edited(parts, duplicate), "duplicate names")


def test_unknown_application(parts) -> None:
    rejected(edited(parts, lambda m: m.update(application="missile_guidance")),
             "unknown application 'missile_guidance'")


def test_format_and_version(parts) -> None:
    rejected(edited(parts, lambda m: m.update(format_version=2)), "format_version 2 is not supported.*newer")
    rejected(edited(parts, lambda m: m.update(format_version="1")), "format_version must be an integer")
    rejected(edited(parts, lambda m: m.update(format="onnx")), "format is 'onnx'")


def test_missing_and_unknown_manifest_keys(parts) -> None:
    rejected(edited(parts, lambda m: m.pop("architecture")), r"missing keys \['architecture'\]")
    rejected(edited(parts, lambda m: m.update(loader="pickle")), r"unknown keys \['loader'\]")
    rejected(edited(parts, lambda m: m.update(environment=[3, 2])), "environment must be an object")
    rejected(edited(parts, lambda m: m["environment"].update(agents={"n": 3})), "environment.agents must be")


def test_manifest_that_is_not_an_object(parts) -> None:
    tensors, _ = parts
    rejected(forge(tensors, None, raw_manifest="[1, 2]"), "manifest must be a JSON object")
    rejected(forge(tensors, None, raw_manifest="{not json"), "manifest is not valid JSON")
    n_header = rewrite_header(forge(tensors, {}), lambda h: h["__metadata__"].update({MANIFEST_KEY: 5}))
    rejected(n_header, "must be a JSON string")


def test_errors_name_the_file(tmp_path, parts) -> None:
    tensors, manifest = parts
    path = tmp_path / "tampered.safetensors"
    path.write_bytes(forge({**tensors, "policy.weight": torch.zeros(9, 84)}, manifest))
    with pytest.raises(BundleError, match=re.escape(str(path))):
        load_bundle(path)
    assert json.loads(json.dumps(read_manifest(forge(tensors, manifest))))  # sanity: the valid one is JSON


# --- fuzzing ---------------------------------------------------------------------------------

@functools.cache
def _fuzz_seed() -> bytes:
    tensors, manifest = valid_parts("lenet5", grid=10)
    return forge(tensors, manifest)


@settings(max_examples=150, deadline=None, database=None)
@given(data=st.data())
def test_any_corruption_loads_cleanly_or_raises_bundle_error(data: st.DataObject) -> None:
    """Random byte edits anywhere (mostly in the header) never escape as another exception."""
    good = _fuzz_seed()
    n = struct.unpack("<Q", good[:8])[0]
    buf = bytearray(good)
    for _ in range(data.draw(st.integers(1, 4), label="edits")):
        if not buf:
            break
        # Bias towards the header, where an edit changes structure rather than just a weight.
        pos = data.draw(st.one_of(st.integers(0, min(8 + n, len(buf)) - 1), st.integers(0, len(buf) - 1)),
                        label="position")
        action = data.draw(st.sampled_from(["flip", "delete", "insert", "truncate"]), label="edit")
        if action == "flip":
            buf[pos] ^= 1 << data.draw(st.integers(0, 7), label="bit")
        elif action == "delete":
            del buf[pos]
        elif action == "insert":
            buf.insert(pos, data.draw(st.integers(0, 255), label="byte"))
        else:
            del buf[pos:]
    try:
        bundle = load_bundle(bytes(buf))
    except BundleError:
        return
    assert bundle.net(torch.zeros(1, *bundle.obs_shape))[0].shape == (1, bundle.num_actions)
