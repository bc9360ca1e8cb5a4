"""`viewscale calibrate capture` through the real drivers: an OpenCV camera reading a video of a
printed ChArUco board (a recording stands in for the camera), before any rig file exists; for
hand-eye shots, the robot service (sim arm) publishing robot/state on a real router. The images
and poses it writes are what `calibrate rig` reads."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from services.calibration.charuco import BoardSpec
from services.calibration.cli import read_gripper_poses
from services.cli import main as viewscale
from services.core.runtime import child_env

ROOT = Path(__file__).resolve().parents[2]
BOARD = BoardSpec()  # the default board: 7x5, 24 corners


@pytest.fixture
def session(tmp_path_factory, zenoh_endpoint) -> Path:
    """A session file: camera F plays a board video, the arm is the sim's, camera.rig not written yet."""
    d = tmp_path_factory.mktemp("capture")
    board = BOARD.image(px_per_square=60)  # (H, W) grey
    frame = np.full((480, 640), 255, np.uint8)
    y, x = (480 - board.shape[0]) // 2, (640 - board.shape[1]) // 2
    frame[y : y + board.shape[0], x : x + board.shape[1]] = board
    video = d / "F.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (640, 480))
    for _ in range(400):  # 20 s at 20 fps: longer than the test takes
        writer.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
    writer.release()
    cfg = {
        "world": "sim",
        "bus": {"mode": "client", "connect": [zenoh_endpoint]},
        "camera": {
            "driver": {"type": "opencv", "cameras": {"F": {"source": str(video)}}},
            "rig": str(d / "lab.yaml"),
            "width": 640,
            "height": 480,
            "fps": 20.0,
        },
        "robot": {"driver": {"type": "sim", "task": "lift"}},
    }
    path = d / "session.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_hand_eye_shots_save_every_camera_and_the_arm_pose_and_add_up(session, tmp_path, capsys):
    images = tmp_path / "calib"
    args = ["calibrate", "capture", "--config", str(session), "--images", str(images), "--kind", "hand_eye"]
    # no robot service publishing yet: refused before any camera is opened, nothing written
    assert viewscale([*args, "--count", "1"]) == 2
    assert "no robot/state on the bus within 5 s: run the router and the robot service" in capsys.readouterr().err
    assert not images.exists()
    robot = subprocess.Popen(
        [sys.executable, "-m", "services.robot", "--config", str(session)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=child_env(),
    )
    try:
        assert robot.stdout.readline().startswith("ready robot")
        _hand_eye_shots(images, args, capsys)
    finally:
        robot.terminate()
        robot.wait(timeout=20)


def _hand_eye_shots(images: Path, args: list[str], capsys) -> None:
    assert viewscale([*args, "--count", "2", "--every", "0"]) == 0
    out = capsys.readouterr().out
    assert "[000] F 24/24 corners, EEF at (0.450, 0.000, 0.250) m" in out, out
    assert "2 shots of hand_eye; with the board: F 2" in out
    assert f"--gripper-poses {images / 'hand_eye_poses.yaml'}" in out
    first = images / "F" / "hand_eye" / "000.png"
    img = cv2.imread(str(first))
    assert img.shape == (480, 640, 3)
    poses = read_gripper_poses(str(images / "hand_eye_poses.yaml"))  # as `calibrate rig --gripper-poses` reads it
    assert sorted(poses) == ["000", "001"]
    assert np.allclose(poses["000"][:3, 3], [0.45, 0.0, 0.25], atol=1e-3)
    assert np.allclose(np.abs(poses["000"][:3, :3]), np.abs(np.diag([1.0, -1.0, -1.0])), atol=1e-3)  # pointing down

    # a second session adds shots: nothing taken before is replaced
    before = first.stat().st_mtime_ns
    assert viewscale([*args, "--count", "1", "--every", "0"]) == 0
    assert "[002] F 24/24 corners" in capsys.readouterr().out
    assert sorted(p.name for p in (images / "F" / "hand_eye").iterdir()) == ["000.png", "001.png", "002.png"]
    assert first.stat().st_mtime_ns == before
    assert sorted(read_gripper_poses(str(images / "hand_eye_poses.yaml"))) == ["000", "001", "002"]

    # a poses file it cannot read is refused before any shot, and kept
    (images / "hand_eye_poses.yaml").write_text("poses: [not, a, mapping]\n")
    assert viewscale([*args, "--count", "1"]) == 2
    assert "holds no 'poses' mapping; move it away to start a new one" in capsys.readouterr().err
    assert len(list((images / "F" / "hand_eye").iterdir())) == 3


def test_interactive_shots_and_bad_arguments(session, tmp_path):
    images = tmp_path / "calib"
    cmd = [sys.executable, "-m", "services.cli", "calibrate", "capture", "--config", str(session)]
    cmd += ["--images", str(images), "--kind", "intrinsics"]
    proc = subprocess.run(cmd, cwd=ROOT, input="\n\nq\n", capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "cameras F: Enter takes a shot, q and Enter ends" in proc.stdout
    assert sorted(p.name for p in (images / "F" / "intrinsics").iterdir()) == ["000.png", "001.png"]
    assert not (images / "hand_eye_poses.yaml").exists()  # no arm needed, none opened
    for extra, says in [
        (["--count", "0"], "error: --count must be at least 1, got 0"),
        (["--set", "sim.x=1"], "error: --set 'sim.x=1' must look like camera.KEY=VALUE or robot.KEY=VALUE"),
        (["--squares", "7"], "error: --squares must look like 7x5, not '7'"),
    ]:
        bad = subprocess.run(cmd + extra, cwd=ROOT, capture_output=True, text=True, timeout=60)
        assert bad.returncode == 2 and bad.stderr.strip() == says, bad.stderr


def test_a_hand_eye_shot_while_the_arm_moves_is_refused():
    from services.calibration.capture import _moved
    from services.core.robot_types import RobotSnapshot

    def at(x: float, quat=(0.0, 1.0, 0.0, 0.0)) -> RobotSnapshot:
        return RobotSnapshot(np.array([x, 0.0, 0.25]), np.array(quat), np.zeros(6), np.zeros(6), 0.0)

    assert _moved(at(0.45), at(0.4505)) is None  # 0.5 mm: still
    assert _moved(at(0.45), at(0.452)).startswith("the arm moved 2.0 mm and 0.00 degrees during the shot")
    turned = (0.0, np.cos(np.radians(0.25)), np.sin(np.radians(0.25)), 0.0)  # 0.5 degrees about z
    assert "0.50 degrees" in _moved(at(0.45), at(0.45, turned))


def test_a_capture_stopped_by_sigterm_keeps_its_shots_whole(session, tmp_path):
    """SIGTERM (a closed terminal's SIGHUP alike) as Ctrl-C: one line, exit 130, and every shot
    saved is a whole image (before: killed on the spot, possibly in the middle of writing one)."""
    images = tmp_path / "calib"
    cmd = [sys.executable, "-m", "services.cli", "calibrate", "capture", "--config", str(session)]
    cmd += ["--images", str(images), "--kind", "intrinsics", "--count", "100", "--every", "0.2"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    shots = 0
    for line in proc.stdout:
        shots += line.startswith("[")  # [000] F 24/24 corners -> .../000.png
        if shots == 2:
            break
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and err.strip() == "interrupted (SIGTERM): the shots taken are kept", err[-2000:]
    saved = sorted((images / "F" / "intrinsics").iterdir())
    assert len(saved) >= 2 and all(cv2.imread(str(p)) is not None for p in saved)
