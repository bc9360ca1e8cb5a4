"""`viewscale collect --auth`: a whole session with every service authenticated as its own user and the
router enforcing deploy/zenoh/router-acl.json5. Every topic of the session still reaches the
recorder, so the ACL lets each service do all it needs (a new topic without its rule fails here)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from services.core.rig import load_rig
from services.recorder.reader import read_episode

ROOT = Path(__file__).resolve().parents[2]


def test_an_authenticated_session_records_every_topic(tmp_path):
    out = tmp_path / "raw"
    cmd = [sys.executable, "-m", "services.cli", "collect", "--out", str(out), "--auth", "--fast"]
    cmd += ["--task", "lift", "--episodes", "1", "--rig", "three15", "--size", "32"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "authenticated, access control on" in proc.stdout and "recorded 1 episodes" in proc.stdout

    (path,) = out.glob("*.mcap")
    ep = read_episode(path)
    ticks = ep.metadata["ticks"]
    assert ep.metadata["success"] is True and ep.flags == [] and ticks > 10
    cameras = sorted(load_rig("three15").names)
    assert ep.cameras == cameras
    for topic in ("/robot/state", "/robot/applied", "/teleop/command", "/sim/task"):
        assert len(ep.messages(topic)) == ticks, topic
    for name in cameras:
        assert len(ep.messages(f"/camera/{name}/image")) == ticks, name
        assert ep.messages(f"/camera/{name}/calibration") and ep.messages(f"/camera/{name}/pose"), name
