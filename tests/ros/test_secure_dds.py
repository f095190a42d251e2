"""What DDS Security the pinned ROS wheels offer: none (docs/security.md, "The finding").

The Fast DDS library of the pinned wheels (ros-fastrtps 2.14.5) is built without its security
plugins, so SROS2 cannot be used: a node given an enclave refuses to start, and security
properties set through a Fast DDS profile are ignored without a word. These tests keep that
finding true: once a wheel with DDS Security is pinned they fail, and docs/security.md's
"SROS2 mode" (a keystore, an enclave per node, `medc-launch --secure`) becomes the thing to build.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from ros_helpers import start_node_process, stop_node_processes

#: The six files SROS2 puts in an enclave (rmw_dds_common's security file names).
ENCLAVE_FILES = ("identity_ca.cert.pem", "cert.pem", "key.pem", "permissions_ca.cert.pem",
                 "governance.p7s", "permissions.p7s")

#: rmw_fastrtps_shared_cpp's error when Fast DDS lacks the security plugins.
NO_SECURITY = "This Fast DDS version doesn't have the security libraries"

#: A node that says whether rclpy could create it (argv[1]: the node name; the rest: ROS args).
NODE_STARTS = """
import sys, rclpy
rclpy.init(args=sys.argv)
try:
    node = rclpy.create_node(sys.argv[1])
except Exception as exc:
    print("NOT STARTED:", exc, flush=True)
    sys.exit(3)
print("STARTED", flush=True)
node.destroy_node()
rclpy.try_shutdown()
"""

#: A talker on chatter until stopped.
#: A talker that ends cleanly on SIGINT: the signal only sets a flag (rclpy's own handler would shut
#: the context down under a spinning executor, and a KeyboardInterrupt can land inside a destructor),
#: so that anything with "Error" in its log comes from the secured participant itself.
TALKER = """
import signal, threading
import rclpy
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import String
stop = threading.Event()
rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
signal.signal(signal.SIGINT, lambda *_: stop.set())
node = rclpy.create_node("secured_talker")
pub = node.create_publisher(String, "chatter", 10)
node.create_timer(0.1, lambda: pub.publish(String(data="team secret")))
print("TALKING", flush=True)
while not stop.is_set():
    rclpy.spin_once(node, timeout_sec=0.1)
node.destroy_node()
rclpy.shutdown()
"""


def _lib_dirs() -> list[Path]:
    prefixes = [sys.prefix, *os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)]
    return [Path(p) / "lib" for p in prefixes if p and (Path(p) / "lib").is_dir()]


def _library(name: str) -> Path:
    for d in _lib_dirs():
        hits = sorted(d.glob(f"{name}.so*"))
        if hits:
            return hits[0].resolve()
    pytest.fail(f"{name}.so not found under {_lib_dirs()}")


def make_keystore(root: Path, enclave: str) -> Path:
    """A keystore laid out as SROS2 lays it (``enclaves/<enclave>/`` with its six files). Their
    content does not matter here: without the plugins the middleware refuses before reading
    them (docs/security.md shows the same with real, openssl-made certificates)."""
    d = root / "enclaves" / enclave.strip("/")
    d.mkdir(parents=True)
    for name in ENCLAVE_FILES:
        (d / name).write_text("placeholder\n")
    return root


def _run_node(args: list[str], env: dict[str, str], timeout_s: float = 120.0):
    return subprocess.run([sys.executable, "-c", NODE_STARTS, *args], env={**os.environ, **env},
                          capture_output=True, text=True, timeout=timeout_s)


def test_fast_dds_in_the_pinned_wheels_is_built_without_dds_security():
    config = next((d.parent / "include" / "fastrtps" / "config.h" for d in _lib_dirs()
                   if (d.parent / "include" / "fastrtps" / "config.h").is_file()), None)
    assert config is not None, "fastrtps/config.h not found"
    assert "#define HAVE_SECURITY 0" in config.read_text()
    fastdds = _library("libfastrtps").read_bytes()
    # The builtin plugins' names (dds.sec.*.plugin values) and their property prefix are absent.
    for plugin in (b"builtin.PKI-DH", b"builtin.Access-Permissions", b"builtin.AES-GCM-GMAC",
                   b"dds.sec."):
        assert plugin not in fastdds, plugin
    assert b"but security is disabled" in fastdds
    assert NO_SECURITY.encode() in _library("librmw_fastrtps_shared_cpp").read_bytes()


@pytest.mark.ros
@pytest.mark.parametrize("strategy", ["Enforce", "Permissive"])
def test_a_node_given_an_enclave_does_not_start(tmp_path, strategy):
    keystore = make_keystore(tmp_path / "keystore", "/medc/agent_0")
    env = {"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": strategy,
           "ROS_SECURITY_KEYSTORE": str(keystore)}
    out = _run_node(["agent_0", "--ros-args", "--enclave", "/medc/agent_0"], env)
    assert out.returncode == 3, out.stdout + out.stderr
    assert "Found security directory" in out.stdout + out.stderr  # rcl found the enclave ...
    assert NO_SECURITY in out.stdout  # ... and the middleware refused it


@pytest.mark.ros
def test_enforce_without_the_enclave_refuses_and_permissive_runs_unsecured(tmp_path):
    missing = {"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_KEYSTORE": str(tmp_path / "none")}
    enforce = _run_node(["agent_0", "--ros-args", "--enclave", "/medc/agent_0"],
                        {**missing, "ROS_SECURITY_STRATEGY": "Enforce"})
    assert enforce.returncode != 0
    assert "SECURITY ERROR" in enforce.stderr and "does not exist" in enforce.stderr
    # Permissive falls back to no security at all: never use it as a guard.
    permissive = _run_node(["agent_0", "--ros-args", "--enclave", "/medc/agent_0"],
                           {**missing, "ROS_SECURITY_STRATEGY": "Permissive"})
    assert permissive.returncode == 0, permissive.stdout + permissive.stderr
    assert "STARTED" in permissive.stdout


@pytest.mark.ros
@pytest.mark.timing
def test_security_properties_in_a_fast_dds_profile_give_no_protection(tmp_path, rclpy_context):
    """Fast DDS's own way to turn security on (dds.sec.* participant properties in an XML
    profile) is parsed and silently ignored: a node without credentials reads the talker."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import String

    enclave = tmp_path / "keystore" / "enclaves" / "talker"
    make_keystore(tmp_path / "keystore", "talker")
    props = {
        "dds.sec.auth.plugin": "builtin.PKI-DH",
        "dds.sec.auth.builtin.PKI-DH.identity_ca": f"file://{enclave}/identity_ca.cert.pem",
        "dds.sec.auth.builtin.PKI-DH.identity_certificate": f"file://{enclave}/cert.pem",
        "dds.sec.auth.builtin.PKI-DH.private_key": f"file://{enclave}/key.pem",
        "dds.sec.access.plugin": "builtin.Access-Permissions",
        "dds.sec.access.builtin.Access-Permissions.permissions_ca":
            f"file://{enclave}/permissions_ca.cert.pem",
        "dds.sec.access.builtin.Access-Permissions.governance": f"file://{enclave}/governance.p7s",
        "dds.sec.access.builtin.Access-Permissions.permissions": f"file://{enclave}/permissions.p7s",
        "dds.sec.crypto.plugin": "builtin.AES-GCM-GMAC",
    }
    properties = "".join(f"<property><name>{k}</name><value>{v}</value></property>" for k, v in props.items())

    def profile(extra: str = "") -> str:
        return ('<?xml version="1.0" encoding="UTF-8"?>\n'
                '<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">'
                '<participant profile_name="secured" is_default_profile="true"><rtps>'
                f'{extra}<propertiesPolicy><properties>{properties}</properties></propertiesPolicy>'
                '</rtps></participant></profiles>\n')

    # The control: this Fast DDS reads the variable (a wrong element in the same profile is reported).
    broken = tmp_path / "broken.xml"
    broken.write_text(profile("<no_such_element/>"))
    control = _run_node(["probe"], {"FASTRTPS_DEFAULT_PROFILES_FILE": str(broken)})
    assert "Error parsing" in control.stdout + control.stderr
    secured = tmp_path / "secured.xml"
    secured.write_text(profile())

    got: list[str] = []
    node = rclpy.create_node("no_credentials")
    node.create_subscription(String, "chatter", lambda m: got.append(m.data), 10)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    log = tmp_path / "talker.log"
    old = os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE")
    os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(secured)
    try:
        talker = start_node_process([sys.executable, "-c", TALKER], log)
    finally:
        if old is None:
            del os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"]
        else:
            os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = old
    try:
        deadline = time.monotonic() + 90.0
        while not got and time.monotonic() < deadline and talker.poll() is None:
            executor.spin_once(timeout_sec=0.1)
    finally:
        stop_node_processes([talker])
        executor.shutdown()
        node.destroy_node()
    text = log.read_text()
    assert "TALKING" in text and "Error" not in text, text
    assert got == ["team secret"] * len(got) and got, "the unauthenticated node read nothing"
