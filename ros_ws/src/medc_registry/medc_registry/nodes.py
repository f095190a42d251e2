"""Local node processes for development and tests: anvil (EVM JSON-RPC) and js-ipfs (Kubo RPC).

Both bind 127.0.0.1 on a free port and dial nothing outside loopback. The binaries come from
``tools/node_modules`` (installed by ``scripts/setup.sh``).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
from medc_common.ros_env import repo_root

from .compile import EVM_VERSION


class NodeError(RuntimeError):
    """A local node could not be found or started."""


def free_port() -> int:
    """A currently free TCP port on 127.0.0.1."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _node_modules() -> Path:
    return repo_root() / "tools" / "node_modules"


def anvil_binary() -> Path:
    """Path of the anvil binary shipped by ``@foundry-rs/anvil-linux-amd64``."""
    found = shutil.which("anvil")
    candidates = [_node_modules() / "@foundry-rs" / "anvil-linux-amd64" / "bin" / "anvil"]
    if found:
        candidates.append(Path(found))
    for path in candidates:
        if path.is_file() and os.access(path, os.X_OK):
            return path
    raise NodeError("anvil not found under tools/node_modules; run `bash scripts/setup.sh`")


def jsipfs_binary() -> Path:
    """Path of js-ipfs's ``jsipfs`` CLI."""
    path = _node_modules() / ".bin" / "jsipfs"
    if not path.exists():
        raise NodeError("jsipfs not found under tools/node_modules; run `bash scripts/setup.sh`")
    return path


def _wait(proc: subprocess.Popen, ready, what: str, timeout: float, log: Path) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise NodeError(f"{what} exited with {proc.returncode}: {log.read_text()[-2000:]}")
        if ready():
            return
        time.sleep(0.25)
    proc.kill()
    raise NodeError(f"{what} not ready after {timeout:.0f} s: {log.read_text()[-2000:]}")


@dataclass
class NodeProcess:
    """A started node: its URL, process and log file. ``stop()`` ends it."""

    url: str
    proc: subprocess.Popen
    log: Path
    extra: dict = field(default_factory=dict)

    @property
    def pid(self) -> int:
        """Process id of the node."""
        return self.proc.pid

    def stop(self, timeout: float = 10.0) -> None:
        """SIGTERM (anvil dumps its state on it), then SIGKILL after ``timeout``."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)


def _rpc_ready(url: str) -> bool:
    try:
        r = httpx.post(
            url, json={"jsonrpc": "2.0", "id": 1, "method": "eth_chainId", "params": []}, timeout=1
        )
        return r.status_code == 200
    except httpx.HTTPError:
        return False


def anvil_command(port: int, state_file: Path | None = None, config_out: Path | None = None) -> list[str]:
    """anvil's command line: loopback, the contracts' hardfork, optional persistent state."""
    cmd = [str(anvil_binary()), "--host", "127.0.0.1", "--port", str(port), "--hardfork", EVM_VERSION]
    cmd += ["--accounts", "10", "--silent"]
    if state_file is not None:
        # Loaded at start, dumped on exit and every few seconds so a hard kill loses little.
        cmd += ["--state", str(state_file), "--state-interval", "2"]
    if config_out is not None:
        cmd += ["--config-out", str(config_out)]
    return cmd


def start_anvil(
    workdir: str | os.PathLike[str],
    state_file: str | os.PathLike[str] | None = None,
    port: int | None = None,
    detach: bool = False,
    timeout: float = 30.0,
) -> NodeProcess:
    """Start anvil on 127.0.0.1; returns once it answers JSON-RPC.

    ``extra["private_keys"]`` holds the funded development keys (from ``--config-out``).
    ``detach=True`` starts it in its own session so it outlives the calling process (CLI use).
    """
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    port = port or free_port()
    config = workdir / "anvil-accounts.json"
    log = workdir / "anvil.log"
    cmd = anvil_command(port, Path(state_file) if state_file else None, config)
    with open(log, "ab") as fh:
        proc = subprocess.Popen(
            cmd, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=detach
        )
    url = f"http://127.0.0.1:{port}"
    _wait(proc, lambda: _rpc_ready(url), "anvil", timeout, log)
    keys = json.loads(config.read_text()).get("private_keys", []) if config.is_file() else []
    return NodeProcess(url, proc, log, {"private_keys": keys})


_POLYFILL = """if (typeof Promise.withResolvers !== 'function') {
  Promise.withResolvers = function () {
    let resolve, reject;
    const promise = new Promise((a, b) => { resolve = a; reject = b; });
    return { promise, resolve, reject };
  };
}
"""


def start_js_ipfs(workdir: str | os.PathLike[str], timeout: float = 120.0) -> NodeProcess:
    """Start a js-ipfs daemon with a fresh repo under ``workdir``, loopback only, offline.

    Returns once ``/api/v0/version`` answers; ``url`` is the RPC API base (``http://127.0.0.1:P``).
    """
    workdir = Path(workdir)
    repo = workdir / "ipfs-repo"
    if repo.exists():
        raise NodeError(f"{repo} exists; js-ipfs needs a fresh repo per run")
    workdir.mkdir(parents=True, exist_ok=True)
    polyfill = workdir / "polyfill.cjs"
    polyfill.write_text(_POLYFILL)
    env = dict(os.environ)
    env["IPFS_PATH"] = str(repo)
    env["NODE_OPTIONS"] = f"--require {polyfill}"
    log = workdir / "jsipfs.log"
    jsipfs = str(jsipfs_binary())
    init = subprocess.run(
        [jsipfs, "init", "--empty-repo"], env=env, capture_output=True, text=True, timeout=120, check=False
    )
    if init.returncode != 0:
        raise NodeError(f"jsipfs init failed: {init.stderr[-2000:]}")
    cfg_path = repo / "config"
    cfg = json.loads(cfg_path.read_text())
    api, gateway, rpc = free_port(), free_port(), free_port()
    cfg["Bootstrap"] = []
    cfg.setdefault("Addresses", {})
    cfg["Addresses"].update(
        {
            "Swarm": [],
            "Delegates": [],
            "API": f"/ip4/127.0.0.1/tcp/{api}",
            "Gateway": f"/ip4/127.0.0.1/tcp/{gateway}",
            "RPC": f"/ip4/127.0.0.1/tcp/{rpc}",
        }
    )
    cfg.setdefault("Discovery", {})
    cfg["Discovery"]["MDNS"] = {"Enabled": False}
    cfg["Discovery"]["webRTCStar"] = {"Enabled": False}
    cfg_path.write_text(json.dumps(cfg, indent=2))
    with open(log, "ab") as fh:
        proc = subprocess.Popen(
            [jsipfs, "daemon"], env=env, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL
        )
    url = f"http://127.0.0.1:{api}"

    def ready() -> bool:
        try:
            return httpx.post(url + "/api/v0/version", timeout=2).status_code == 200
        except httpx.HTTPError:
            return False

    _wait(proc, ready, "js-ipfs daemon", timeout, log)
    return NodeProcess(url, proc, log, {"gateway": f"http://127.0.0.1:{gateway}", "repo": str(repo)})
