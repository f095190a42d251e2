"""Compile the MEDC contracts with solcjs (npm solc, pinned) and read the committed artifacts.

The artifacts under ``contracts/artifacts/`` (ABI + creation bytecode per contract) are committed so
the registry runs without a compiler; ``python -m medc_registry.compile`` regenerates them and a test
checks they match a fresh compile whenever ``tools/node_modules/solc`` is present.

Compiler settings are fixed here: solc 0.8.28, evmVersion ``cancun`` (accepted by eth-tester's
py-evm, anvil and current Besu/Quorum), the via-IR pipeline with the optimizer at 50 runs (the
allocation loop needs via-IR; few runs favour deployment size), and no CBOR metadata, so the
bytecode depends only on the code, not on comments or file paths.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from medc_common.ros_env import repo_root

SOLC_VERSION = "0.8.28"
EVM_VERSION = "cancun"
OPTIMIZER_RUNS = 50

#: Sources and the contracts of each written to the artifacts directory (source file -> contract
#: names); ``MedcShared.sol`` holds what both contracts share (constants, errors) and writes none.
SOURCES = {
    "src/MedcShared.sol": [],
    "src/UsersManager.sol": ["UsersManager"],
    "src/ModelsManager.sol": ["ModelsManager"],
    "test/ReentrantWithdrawer.sol": ["ReentrantWithdrawer"],
}


class CompileError(RuntimeError):
    """The Solidity compiler is missing or reported errors."""


def contracts_dir() -> Path:
    """``contracts/`` of the repository."""
    return repo_root() / "contracts"


def artifacts_dir() -> Path:
    """Where the committed ABI/bytecode JSON files live."""
    return contracts_dir() / "artifacts"


def standard_json_input() -> dict[str, Any]:
    """The solc standard-JSON input for every source in :data:`SOURCES`."""
    base = contracts_dir()
    sources = {name: {"content": (base / name).read_text()} for name in SOURCES}
    return {
        "language": "Solidity",
        "sources": sources,
        "settings": {
            "evmVersion": EVM_VERSION,
            "viaIR": True,
            "optimizer": {"enabled": True, "runs": OPTIMIZER_RUNS},
            "metadata": {"bytecodeHash": "none", "appendCBOR": False},
            "outputSelection": {"*": {"*": ["abi", "evm.bytecode.object"]}},
        },
    }


def solc_module_dir() -> Path:
    """``tools/node_modules/solc`` (raises CompileError when absent)."""
    path = repo_root() / "tools" / "node_modules" / "solc"
    if not (path / "index.js").is_file():
        raise CompileError(f"solc not installed at {path}; run `bash scripts/setup.sh`")
    return path


def compile_contracts() -> dict[str, dict[str, Any]]:
    """Compile all sources with solcjs; returns ``{name: {"abi": [...], "bytecode": "0x..."}}``."""
    solc = solc_module_dir()
    script = (
        "const solc=require(process.argv[1]);let s='';process.stdin.on('data',d=>s+=d);"
        "process.stdin.on('end',()=>{if(!solc.version().startsWith(process.argv[2]))"
        "{console.error('wrong solc '+solc.version());process.exit(2)}"
        "process.stdout.write(solc.compile(s))});"
    )
    proc = subprocess.run(
        ["node", "-e", script, str(solc), SOLC_VERSION],
        input=json.dumps(standard_json_input()),
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    if proc.returncode != 0:
        raise CompileError(f"solcjs failed: {proc.stderr.strip()}")
    out = json.loads(proc.stdout)
    errors = [e for e in out.get("errors", []) if e.get("severity") == "error"]
    if errors:
        raise CompileError("\n".join(e.get("formattedMessage", e.get("message", "")) for e in errors))
    result: dict[str, dict[str, Any]] = {}
    for source, names in SOURCES.items():
        for name in names:
            c = out["contracts"][source][name]
            result[name] = {
                "contractName": name,
                "source": f"contracts/{source}",
                "compiler": {
                    "solc": SOLC_VERSION,
                    "evmVersion": EVM_VERSION,
                    "optimizerRuns": OPTIMIZER_RUNS,
                },
                "abi": c["abi"],
                "bytecode": "0x" + c["evm"]["bytecode"]["object"],
            }
    return result


def artifact_text(artifact: dict[str, Any]) -> str:
    """Canonical file text of one artifact (stable key order, trailing newline)."""
    return json.dumps(artifact, indent=1, sort_keys=True) + "\n"


def write_artifacts(target: Path | None = None) -> list[Path]:
    """Compile and write ``<Name>.json`` files; returns the written paths."""
    target = target or artifacts_dir()
    target.mkdir(parents=True, exist_ok=True)
    written = []
    for name, artifact in compile_contracts().items():
        path = target / f"{name}.json"
        path.write_text(artifact_text(artifact))
        written.append(path)
    return written


def load_artifact(name: str) -> dict[str, Any]:
    """The committed artifact of contract ``name`` (ABI and bytecode)."""
    path = artifacts_dir() / f"{name}.json"
    if not path.is_file():
        raise CompileError(f"missing artifact {path}; run `python -m medc_registry.compile`")
    return json.loads(path.read_text())


def main(argv: list[str] | None = None) -> int:
    """Regenerate the committed artifacts."""
    del argv
    for path in write_artifacts():
        print(path.relative_to(repo_root()))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
