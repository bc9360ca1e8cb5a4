"""`viewscale check --config ...` as a lab runs it before a session: every camera, the calibration
and the robot, through the same driver registry the services use; a plain-words line per
finding and a non-zero exit when anything fails. The sim drivers stand in for hardware here
(world: sim), and a video-file camera that does not exist stands in for an unplugged one."""

from __future__ import annotations

from pathlib import Path

import yaml
from cli_process import viewscale, viewscale_each

from services.camera.config import CameraConfig
from services.session.check import CameraReport, camera_findings

ROOT = Path(__file__).resolve().parents[2]


def sim_config(tmp_path: Path, **camera) -> Path:
    cfg = {
        "world": "sim",
        "camera": {"driver": {"type": "sim", "task": "lift"}, "rig": "three15", "width": 64, "height": 64, "fps": 10.0}
        | camera,
        "robot": {"driver": {"type": "sim", "task": "lift"}},
    }
    path = tmp_path / "session.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_a_working_sim_rig_passes_every_part(tmp_path):
    proc = viewscale("check", "--config", str(sim_config(tmp_path)), "--seconds", "1")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    for name in ("F", "FL", "FR"):
        [line] = [ln for ln in lines if f"camera {name} " in ln]
        assert line.startswith("ok"), line
        assert "64x64" in line and "fps of 10 asked" in line, line
    [robot] = [ln for ln in lines if "robot" in ln and "EEF at" in ln]
    assert robot.startswith("ok"), robot
    assert any(ln.startswith("ok") and "calibration" in ln for ln in lines), proc.stdout
    assert lines[-1].endswith("0 failed"), lines[-1]


def test_an_arm_outside_the_workspace_and_a_missing_camera_fail_in_plain_words(tmp_path):
    cfg = sim_config(tmp_path, driver={"type": "opencv", "cameras": {"F": {"source": str(tmp_path / "none.mp4")}}})
    proc = viewscale(
        "check",
        "--config",
        str(cfg),
        "--seconds",
        "1",
        "--set",
        "robot.safety.workspace_lo=[0.15,-0.45,0.5]",
        "--set",
        "robot.safety.workspace_hi=[0.8,0.45,0.9]",
    )
    assert proc.returncode == 1, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    [cam] = [ln for ln in lines if ln.startswith("FAIL") and "camera" in ln]
    assert "none.mp4" in cam, cam
    [robot] = [ln for ln in lines if ln.startswith("FAIL") and "robot" in ln]
    assert "outside the safety workspace on z" in robot, robot
    assert "Traceback" not in proc.stderr


def test_bad_arguments_are_one_error_line(tmp_path):
    proc = viewscale("check", "--config", str(sim_config(tmp_path)), "--only", "cameras,wheels")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == ["error: --only wheels: choose from cameras, calibration, robot, policy"]
    cases = [
        (["--seconds", "0"], "error: --seconds must be positive, got 0"),  # was 7 FAIL lines
        # taken before; on a real rig every camera's calibration would have failed
        (["--max-error-px", "-1"], "error: --max-error-px must be positive, got -1"),
        (["--max-age-days", "-3"], "error: --max-age-days must be 0 or more, got -3"),
        (["--only", ","], "error: --only ,: choose from cameras, calibration, robot, policy"),  # was '--only : ...'
        # a section check reads nothing of (before: ignored without a word, exit 0)
        (
            ["--set", "sim.x=1"],
            "error: --set 'sim.x=1' must look like camera.KEY=VALUE or robot.KEY=VALUE or teleop.KEY=VALUE",
        ),
    ]
    procs = viewscale_each([["check", "--config", str(sim_config(tmp_path)), *args] for args, _ in cases])
    for (args, says), proc in zip(cases, procs):
        assert proc.returncode == 2, args
        assert proc.stderr.strip().splitlines() == [says]
    proc = viewscale("check", "--config", str(tmp_path / "missing.yaml"))
    assert proc.returncode == 2
    assert proc.stderr.strip().startswith("error: config file") and "Traceback" not in proc.stderr
    proc = viewscale(
        "check", "--config", str(sim_config(tmp_path, rig=str(tmp_path / "lab.yaml"))), "--only", "cameras,calibration"
    )
    assert proc.returncode == 1, proc.stdout + proc.stderr
    [line] = [ln for ln in proc.stdout.splitlines() if ln.startswith("FAIL  calibration")]
    assert "lab.yaml" in line and "no rig file" in line and line.count("viewscale calibrate rig") == 1, line


def test_a_camera_below_its_rate_fails_and_one_that_delivers_nothing_says_so():
    cfg = CameraConfig(fps=30.0)
    slow = CameraReport("F", frames=40, fps=20.0, size=(84, 84), native=(640, 480), latency_ms=35.0, exposure=None)
    fine = CameraReport("FL", frames=90, fps=29.5, size=(84, 84), native=None, latency_ms=None, exposure=156.0)
    dead = CameraReport("FR", frames=0, fps=0.0, size=None, native=None, latency_ms=None, exposure=None)
    f_slow, f_fine, f_dead = camera_findings(cfg, [slow, fine, dead], min_fps_fraction=0.9)
    assert not f_slow.ok and "20.0 fps of 30 asked" in f_slow.text and "device 640x480, resized" in f_slow.text
    assert f_fine.ok and "exposure 156" in f_fine.text
    assert not f_dead.ok and "no frame" in f_dead.text


def test_cameras_are_checked_before_their_rig_file_is_written(tmp_path):
    """Step 2 of a lab's set-up: cameras mounted, not calibrated yet (before: with no rig file, the
    cameras were left out without a line)."""
    import cv2
    import numpy as np

    video = tmp_path / "F.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (160, 120))
    for n in range(60):
        writer.write(np.full((120, 160, 3), 4 * n, np.uint8))
    writer.release()
    cfg = sim_config(
        tmp_path, rig=str(tmp_path / "lab.yaml"), driver={"type": "opencv", "cameras": {"F": {"source": str(video)}}}
    )
    proc = viewscale("check", "--config", str(cfg), "--seconds", "1", "--only", "cameras,calibration")
    assert proc.returncode == 1, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    assert [ln.split()[:3] for ln in lines[:2]] == [["FAIL", "calibration", "camera.rig"], ["ok", "camera", "F"]], lines
    assert "160x120" in lines[1] or "64x64" in lines[1], lines[1]
    proc = viewscale("check", "--config", str(cfg), "--seconds", "1", "--only", "cameras")
    assert proc.returncode == 0, proc.stdout + proc.stderr  # what was asked for passes
    assert proc.stdout.splitlines()[-1] == "1 ok, 0 failed"
    # a driver that names no cameras (the sim's) cannot be opened without its rig: said, not skipped
    proc = viewscale(
        "check", "--config", str(sim_config(tmp_path, rig=str(tmp_path / "lab.yaml"))), "--only", "cameras,calibration"
    )
    assert proc.returncode == 1 and "FAIL  cameras        sim: not checked: they need camera.rig" in proc.stdout


def test_a_stream_that_refuses_is_said_once_in_plain_words(tmp_path):
    """(OpenCV's own `[ WARN:0@0.2] global cap.cpp:212 open VIDEOIO(FFMPEG): backend is generally
    available but can't be used to capture by name` came first on stderr)"""
    cfg = tmp_path / "lab.yaml"
    cfg.write_text(
        yaml.safe_dump(
            {
                "world": "real",
                "camera": {
                    "rig": "front",
                    "driver": {"type": "opencv", "cameras": {"F": {"source": "rtsp://127.0.0.1:1/x"}}},
                },
            }
        )
    )
    proc = viewscale("check", "--config", str(cfg), "--only", "cameras")
    assert (
        proc.returncode == 1
        and "FAIL  cameras        opencv: camera F: cannot open rtsp://127.0.0.1:1/x" in proc.stdout
    )
    assert "WARN" not in proc.stdout + proc.stderr, proc.stderr


def test_the_policy_a_session_drives_with_is_checked_against_the_session(tiny_checkpoint, tmp_path):
    """A session whose teleop drives with a policy: its server answers, and the policy fits the
    session (views that are cameras here, at the frame size and control rate it was trained at,
    placed where the server has them). Before, nothing looked: a wrong size failed every GetAction
    in the session, a wrong rate moved the arm 1.5x as fast, a moved camera turned its actions."""
    from services.session.evaluate import PolicyServer

    moved = tmp_path / "moved.yaml"
    moved.write_text("name: moved\ncameras:\n  F: {yaw_deg: 5}\n  FL: {yaw_deg: 15}\n  FR: {yaw_deg: -15}\n")
    cfg = sim_config(tmp_path, width=32, height=32)
    data = yaml.safe_load(cfg.read_text())
    with PolicyServer(str(tiny_checkpoint), tmp_path / "serve", None, 0, "three15", "lift") as server:
        data["teleop"] = {"driver": {"type": "policy", "server": server.address, "views": ["F", "FL"]}}
        cfg.write_text(yaml.safe_dump(data))
        proc = viewscale("check", "--config", str(cfg), "--only", "policy")
        assert proc.returncode == 0, proc.stdout + proc.stderr
        lines = proc.stdout.splitlines()
        assert lines[0].startswith("ok    policy") and "camera space, views F,FL, trained at 20 Hz" in lines[0]
        assert [ln.split()[3] for ln in lines[1:3]] == ["F", "FL"] and "placed as the server has it" in lines[1]

        proc = viewscale(
            "check", "--config", str(cfg), "--only", "policy", "--set", "robot.control_hz=30",
            "--set", "camera.width=64", "--set", "camera.height=64",
        )  # fmt: skip
        assert proc.returncode == 1, proc.stdout
        fails = [ln for ln in proc.stdout.splitlines() if ln.startswith("FAIL")]
        assert "trained at 20 Hz, the robot ticks at 30 Hz" in fails[0] and "set robot.control_hz to 20" in fails[0]
        assert "sends 64x64 frames, the policy server expects 32x32" in fails[1] and len(fails) == 3

        proc = viewscale("check", "--config", str(cfg), "--only", "policy", "--set", f"camera.rig={moved}")
        assert proc.returncode == 1, proc.stdout
        [fail] = [ln for ln in proc.stdout.splitlines() if ln.startswith("FAIL")]
        assert fail.startswith("FAIL  policy view F ") and "5.00 degrees away" in fail and f"--rig {moved}" in fail
    proc = viewscale("check", "--config", str(cfg), "--only", "policy", "--set", "teleop.driver.connect_timeout_s=2")
    assert proc.returncode == 1 and "no policy server at" in proc.stdout, proc.stdout  # (the server stopped)
    data["teleop"] = {"driver": {"type": "keyboard"}}
    cfg.write_text(yaml.safe_dump(data))
    proc = viewscale("check", "--config", str(cfg), "--seconds", "1")  # no policy: not checked, not failed
    assert proc.returncode == 0 and "policy" not in proc.stdout, proc.stdout
    proc = viewscale("check", "--config", str(cfg), "--only", "policy")
    assert proc.returncode == 1 and "teleop.driver.type is keyboard, not policy" in proc.stdout
