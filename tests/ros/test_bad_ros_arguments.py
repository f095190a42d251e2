"""Every node refuses a ROS argument it cannot use (a bad namespace remap, a remap rule or a
parameter override rcl cannot parse, an unquoted value with a space, a value of the wrong type, a
folder parameter naming a device) with one line of its own naming the argument and status 2, before
it serves anything: no rclpy traceback, no rcl log lines."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BIN = Path(sys.executable).parent


@pytest.mark.ros
@pytest.mark.parametrize(
    ("script", "ros_args", "message"),
    [
        ("medc-agent", ["-r", "__ns:=/te am"],
         "-r __ns:=/te am: namespace '/te am' is not a valid ROS namespace"),
        ("medc-sim", ["-r", "__ns:=/te am"],
         "-r __ns:=/te am: namespace '/te am' is not a valid ROS namespace"),
        ("medc-bridge", ["-r", "__ns:=/te am"],
         "-r __ns:=/te am: namespace '/te am' is not a valid ROS namespace"),
        ("medc-sim", ["-r", "__ns:=team2"], "-r __ns:=team2: a node namespace must be fully qualified"),
        ("medc-agent", ["-r", "__ns:=/te", "am"], "unknown ROS arguments ['am']"),
        ("medc-agent", ["-r", "__node:=9x"], "Couldn't parse remap rule: '-r __node:=9x'"),
        ("medc-sim", ["-p", "grid:=[1,"], "Couldn't parse parameter override rule: '-p grid:=[1,'"),
        ("medc-sim", ["-p", "grid:=hello"], "-p grid:=hello: that is text; grid takes an integer"),
        ("medc-agent", ["-p", "policy:=greedy", "-p", "agents:=true"],
         "-p agents:=True: that is true or false; agents takes an integer"),
        ("medc-sim", ["-p", "resolution:=0.0"], "resolution must be a finite number > 0, got 0.0"),
        ("medc-sim", ["-p", "move_timeout_s:=nan"],
         "move_timeout_s must be a finite number of seconds >= 0, got nan"),
        ("medc-agent", ["-p", "policy:=greedy", "-p", "agents:=3", "-p", "grid:=10", "-p",
                        "lost_timeout_s:=-1.0"],
         "lost_timeout_s must be a finite number of seconds >= 0, got -1.0"),
        ("medc-bridge", ["-p", "cache_dir:=/dev/full"],
         "cache_dir: /dev/full is not a folder: give a folder to write into"),
        ("medc-bridge", ["-p", "content:=/dev/full"],
         "content store: /dev/full is not a folder: give a folder to write into"),
    ],
)
def test_a_bad_ros_argument_is_one_line_of_the_nodes_own(script, ros_args, message):
    out = subprocess.run([str(BIN / script), "--ros-args", *ros_args], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    assert lines[0].startswith(f"{script}: ") and message in lines[0], lines[0]
    assert "Traceback" not in out.stderr and "[rcl]" not in out.stderr


def test_stderr_is_restored_after_a_refused_start(capfd):
    """rcl's log lines of a failed start are dropped, and stderr works as before afterwards; a start
    that works brings rclpy up."""
    import rclpy
    from medc_common.executors import BadRosArguments, init_ros

    with pytest.raises(BadRosArguments, match=r"Couldn't parse remap rule: '-r foo:=bar baz'"):
        init_ros(["x", "--ros-args", "-r", "foo:=bar baz"])
    print("after", file=sys.stderr, flush=True)
    err = capfd.readouterr().err
    assert err == "after\n"
    init_ros(["x", "--ros-args", "-r", "__ns:=/team2"])
    try:
        assert rclpy.ok()
    finally:
        rclpy.try_shutdown()
