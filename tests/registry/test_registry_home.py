"""The registry home (medc_registry.home): a home folder or a spec of strings gives one set of
settings, and every user (CLI, bridge node, demo) opens its chain and store through it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from medc_registry import KuboContentStore, LocalContentStore, Registry
from medc_registry.home import (
    ANVIL_ACCOUNTS_FILE,
    PENDING_FILE,
    RegistryHomeError,
    home_keys,
    home_settings,
    save_state,
    spec_settings,
)
from registry_helpers import APP, PRICE

KEY_A, KEY_B, KEY_C = ("0x" + c * 64 for c in "abc")


def test_a_spec_names_the_store_and_the_chain(tmp_path: Path) -> None:
    local = spec_settings("embedded", str(tmp_path / "store"))
    assert local.embedded and local.keys == () and local.pending_file is None
    assert isinstance(local.open_store(), LocalContentStore)
    assert local.content == {"kind": "local", "root": str(tmp_path / "store")}
    fresh = spec_settings("embedded")
    assert fresh.content["kind"] == "local" and Path(fresh.content["root"]).is_dir()
    kubo = spec_settings("embedded", "http://127.0.0.1:5001")
    assert isinstance(kubo.open_store(), KuboContentStore)

    keys = tmp_path / "keys.txt"
    keys.write_text(f"{KEY_A}\n\n  {KEY_B}  \n")
    remote = spec_settings("http://10.0.0.5:8545", str(tmp_path), "0xUsers", "0xModels", str(keys))
    assert (remote.chain, remote.keys, remote.embedded) == ("http://10.0.0.5:8545", (KEY_A, KEY_B), False)
    assert (remote.users_manager, remote.models_manager) == ("0xUsers", "0xModels")


@pytest.mark.parametrize(
    ("chain", "content", "addresses", "key_file", "loopback_only", "words"),
    [
        ("http://10.0.0.5:8545", "", ("0xU", "0xM"), "keys", True, "or a JSON-RPC URL on loopback"),
        ("embedded", "http://ipfs.example.com:5001", ("", ""), "", True, "content API .* on loopback"),
        ("ws://127.0.0.1:8545", "", ("0xU", "0xM"), "keys", False, r"JSON-RPC URL \(http or https\)"),
        ("http://127.0.0.1:8545", "", ("", "0xM"), "keys", False, "contract addresses are required"),
        ("http://127.0.0.1:8545", "", ("0xU", "0xM"), "missing", False, "cannot read private key file"),
        ("http://127.0.0.1:8545", "", ("0xU", "0xM"), "empty", False, "holds no key"),
    ],
)
def test_a_spec_that_cannot_work_says_why(
    tmp_path, chain, content, addresses, key_file, loopback_only, words
) -> None:
    (tmp_path / "keys").write_text(KEY_A + "\n")
    (tmp_path / "empty").write_text("\n\n")
    with pytest.raises(RegistryHomeError, match=words):
        spec_settings(chain, content, *addresses, str(tmp_path / key_file) if key_file else "",
                      loopback_only=loopback_only)


def test_an_embedded_spec_opens_a_registry_on_the_given_store(tmp_path: Path) -> None:
    reg = Registry.from_settings(spec_settings("embedded", str(tmp_path / "store")), account=1)
    assert reg.address == reg.chain.addresses[1] and reg.pending.path is None
    reg.register_user()
    model = reg.share_model(b"expert bytes", APP, {"agents": 1, "walls": 3}, PRICE)
    assert (tmp_path / "store").is_dir() and reg.fetch(model.cid) == b"expert bytes"
    with pytest.raises(ValueError, match="account index 10 out of range"):
        Registry.from_settings(spec_settings("embedded", str(tmp_path / "store")), account=10)


def test_a_home_without_a_registry_says_what_to_run(tmp_path: Path) -> None:
    with pytest.raises(RegistryHomeError, match="run `medc-registry start`"):
        home_settings(tmp_path / "nowhere")
    with pytest.raises(RuntimeError, match="medc-registry deploy --rpc URL"):
        Registry.from_home(str(tmp_path / "nowhere"))


def test_a_home_records_chain_store_keys_and_pending_requests(tmp_path: Path, monkeypatch) -> None:
    home = tmp_path / "home"
    keys = tmp_path / "keys.txt"
    keys.write_text(f"{KEY_B}\n")
    state = {"rpc_url": "http://127.0.0.1:1", "poa": True, "key_file": str(keys), "node": {"pid": 1},
             "users_manager": "0xU", "models_manager": "0xM"}
    save_state(home, state)
    (home / ANVIL_ACCOUNTS_FILE).write_text(json.dumps({"private_keys": [KEY_C]}))
    monkeypatch.setenv("MEDC_PRIVATE_KEY", f" {KEY_A}\n")
    settings = home_settings(home)
    assert settings.keys == (KEY_A, KEY_B, KEY_C) == tuple(home_keys(home, state))
    assert settings.content == {"kind": "local", "root": str(home / "content")}
    assert settings.poa and settings.local_node and settings.pending_file == home / PENDING_FILE
    monkeypatch.setenv("MEDC_HOME", str(home))
    assert home_settings() == settings
    # The node is not running: the error says how to bring it back.
    with pytest.raises(RegistryHomeError, match="run `medc-registry start` to restart the local node"):
        settings.open_chain(deadline=0.5)
