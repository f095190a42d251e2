"""The MCAP file of medc-record (and medc-launch --record) against hostile targets: an existing file
or a planted link is refused unless --overwrite (the link then replaced, never written through); a
folder, /dev/full, a name too long, a missing folder or one it cannot write are refused before the
mission in one line, status 2, nothing written; a full disk mid-mission stops the recording in one
line and leaves no half file."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from child_signals import default_sigint

BIN = Path(sys.executable).parent
#: Seconds a loaded machine is given for what these tests wait on (the deadline, not a sleep).
DEADLINE_S = 120.0


def _record_main(capsys, *args: str) -> tuple[int, str]:
    from medc_bringup.recorder import main

    code = main([*map(str, args)])
    return code, capsys.readouterr().err


def _one_line(err: str, program: str = "medc-record") -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{program}: ") and "Traceback" not in err, err
    return lines[0]


def _listing(folder: Path) -> dict[str, bytes | str]:
    """Each entry of ``folder``: a link's target, a file's bytes."""
    return {p.name: (f"-> {os.readlink(p)}" if p.is_symlink() else p.read_bytes() if p.is_file() else "dir")
            for p in folder.iterdir()}


@pytest.mark.parametrize("target", ["existing file", "planted link", "folder", "/dev/full", "long name",
                                    "missing folder", "unwritable folder"])
def test_an_unusable_target_is_refused_before_the_mission(tmp_path, capsys, target):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    out = tmp_path / "mission.mcap"
    expected = {
        "existing file": "exists (a file): not overwritten; give --overwrite to replace it",
        "planted link": "exists (a link): not overwritten; give --overwrite to replace it",
        "folder": "is a folder: give the file to write",
        "/dev/full": "is not a regular file (a device, FIFO or socket)",
        "long name": "the name is longer than the",
        "missing folder": "does not exist",
        "unwritable folder": "is not writable" if os.geteuid() != 0 else "Permission denied",
    }[target]
    if target == "existing file":
        out.write_bytes(b"last week's mission\n")
    elif target == "planted link":
        out.symlink_to(victim)
    elif target == "folder":
        out = tmp_path
    elif target == "/dev/full":
        out = Path("/dev/full")
    elif target == "long name":
        out = tmp_path / ("m" * 300 + ".mcap")
    elif target == "missing folder":
        out = tmp_path / "nowhere" / "mission.mcap"
    else:  # root writes wherever the mode says it may not: /sys refuses everyone
        out = Path("/sys/mission.mcap") if os.geteuid() == 0 else tmp_path / "ro" / "mission.mcap"
        if os.geteuid() != 0:
            out.parent.mkdir(mode=0o500)
    before = _listing(tmp_path)
    start = time.monotonic()
    code, err = _record_main(capsys, "-o", out)
    assert code == 2
    assert expected in _one_line(err)
    assert time.monotonic() - start < DEADLINE_S  # refused at once: no node, no waiting for a graph
    assert _listing(tmp_path) == before  # nothing written, no temporary file left
    assert victim.read_text() == "precious\n"
    if target == "/dev/full":
        assert Path("/dev/full").is_char_device()


def test_launch_refuses_its_record_file_before_the_mission(bundles, tmp_path, capsys):
    from medc_bringup.launcher import main

    config = tmp_path / "launch.yaml"
    config.write_text(f"grid: 10\nwalls: 1\nmax_steps: 20\nseed: 3\npolicy: {bundles['a']}\n")
    existing = tmp_path / "run.mcap"
    existing.write_bytes(b"kept\n")
    code = main(["--config", str(config), "--episodes", "1", "--record", str(existing)])
    err = capsys.readouterr().err
    assert code == 2
    assert "--record" in _one_line(err, "medc-launch") and "exists (a file): not overwritten" in err
    assert existing.read_bytes() == b"kept\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["launch.yaml", "run.mcap"]


def test_a_full_disk_mid_mission_stops_the_recording_without_a_half_file(tmp_path):
    from medc_bringup.recorder import finish_recording, open_recording
    from rclpy.qos import QoSProfile

    output, target, recording = open_recording(str(tmp_path / "mission.mcap"))
    recording.add_topic("/medc/note", "std_msgs/msg/String", QoSProfile(depth=1))

    def full(*_a, **_k):
        raise OSError(errno.ENOSPC, "No space left on device")

    recording._writer.add_message = full
    recording.write("/medc/note", b"\x00\x01\x00\x00\x02\x00\x00\x00a\x00")
    recording.write("/medc/note", b"\x00\x01\x00\x00\x02\x00\x00\x00b\x00")  # not tried again
    assert recording.failed == "No space left on device"
    said = finish_recording(recording, target)
    assert said == f"the recording stopped: cannot write {output}: No space left on device"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.ros
@pytest.mark.timing
def test_overwrite_replaces_a_planted_link_and_keeps_what_was_recorded(rclpy_context, tmp_path):
    """medc-record -o LINK --overwrite: the recording replaces the link (its target untouched) and
    holds the message published while it ran."""
    import rclpy
    from mcap_ros2.reader import read_ros2_messages
    from rclpy.qos import DurabilityPolicy, QoSProfile
    from std_msgs.msg import String

    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    out = tmp_path / "mission.mcap"
    out.symlink_to(victim)
    ns = "/rec_targets"
    node = rclpy.create_node("note_taker", namespace=ns)
    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pub = node.create_publisher(String, f"{ns}/note", latched)
    pub.publish(String(data="kept"))
    proc = subprocess.Popen([str(BIN / "medc-record"), "-o", str(out), "--overwrite", "--namespace", ns],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=default_sigint)
    try:
        deadline = time.monotonic() + DEADLINE_S
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.05)
        assert pub.get_subscription_count() > 0, "the recorder never subscribed to the note"
        assert out.is_symlink()  # the recording is in its temporary file while the mission runs
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=DEADLINE_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        node.destroy_node()
    assert proc.returncode == 0, stderr
    assert "Traceback" not in stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["output"] == str(out) and summary["file_bytes"] == out.stat().st_size > 0
    assert not out.is_symlink() and out.read_bytes()[:5] == b"\x89MCAP"
    assert victim.read_text() == "precious\n"
    notes = [m.ros_msg.data for m in read_ros2_messages(str(out)) if m.channel.topic == f"{ns}/note"]
    assert notes == ["kept"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mission.mcap", "victim.txt"]


@pytest.mark.parametrize("target", ["folder", "/dev/full", "long name", "missing folder"])
def test_launch_refuses_an_unusable_key_file_before_the_mission(bundles, tmp_path, capsys, monkeypatch,
                                                                target):
    from medc_bringup.launcher import main
    from medc_common import auth

    monkeypatch.delenv(auth.KEY_FILE_ENV, raising=False)
    key = {"folder": tmp_path, "/dev/full": Path("/dev/full"), "long name": tmp_path / ("k" * 300),
           "missing folder": tmp_path / "nowhere" / "mission.key"}[target]
    expected = {"folder": "is not a regular file", "/dev/full": "is not a regular file",
                "long name": "File name too long", "missing folder": "No such file or directory"}[target]
    before = _listing(tmp_path)
    code = main(["--policy", str(bundles["a"]), "--episodes", "1", "--authenticate", "--key-file", str(key)])
    assert code == 2
    assert expected in _one_line(capsys.readouterr().err, "medc-launch")
    assert _listing(tmp_path) == before
    assert auth.KEY_FILE_ENV not in os.environ


@pytest.mark.parametrize("target", ["file", "/dev/full", "long name"])
def test_the_demo_refuses_an_unusable_output_folder_before_its_first_step(tmp_path, capsys, target):
    from medc_bringup.demo import main

    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    out = {"file": victim, "/dev/full": Path("/dev/full"), "long name": tmp_path / ("d" * 300)}[target]
    code = main(["--quick", "--no-ros", "--quiet", "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 1 and ("is not a folder" in captured.err or "bytes the file system takes" in captured.err)
    _one_line(captured.err, "medc-demo")
    error = captured.err.strip()[len("medc-demo: error: "):]
    assert json.loads(captured.out) == {"ok": False, "error": error}
    assert sorted(os.listdir(tmp_path)) == ["victim.txt"] and victim.read_text() == "precious\n"
