"""The committed ABI/bytecode equal a fresh compile with the pinned solc and explicit evmVersion."""

from __future__ import annotations

import pytest
from medc_registry import compile as solc


def test_committed_artifacts_match_a_fresh_compile():
    try:
        solc.solc_module_dir()
    except solc.CompileError as exc:
        pytest.skip(str(exc))
    fresh = solc.compile_contracts()
    for name, artifact in fresh.items():
        committed = (solc.artifacts_dir() / f"{name}.json").read_text()
        assert committed == solc.artifact_text(artifact), (
            f"{name}.json is stale: run `python -m medc_registry.compile` and commit contracts/artifacts"
        )


def test_artifacts_pin_compiler_and_evm_version():
    for name in ("UsersManager", "ModelsManager"):
        art = solc.load_artifact(name)
        assert art["compiler"] == {
            "solc": "0.8.28",
            "evmVersion": "cancun",
            "optimizerRuns": solc.OPTIMIZER_RUNS,
        }
        assert art["bytecode"].startswith("0x") and len(art["bytecode"]) > 1000
    assert solc.standard_json_input()["settings"]["evmVersion"] == "cancun"
