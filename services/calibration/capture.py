"""``viewscale calibrate capture``: take the calibration images ``calibrate rig`` reads (the
cameras through their drivers; for ``hand_eye``, the arm's pose from ``robot/state`` on the bus).
What it does, for its user: ``CAPTURE_DESCRIPTION`` in ``cli.py`` (its ``--help``)."""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from services.calibration.charuco import IMAGE_KINDS, BoardSpec, CalibrationError, detect
from services.camera.base import Frame
from services.camera.config import CAMERA_DRIVERS, CameraConfig, stand_in_rig
from services.core import topics
from services.core.bus import Bus
from services.core.clock import now_ns
from services.core.config import ConfigError, load_config
from services.core.geometry import quat_wxyz_to_matrix, rotation_error
from services.core.rig import load_rig
from services.pb.sensors_pb2 import RobotState
from services.robot.config import RobotConfig

POSES_FILE = "hand_eye_poses.yaml"
FRAME_TIMEOUT_S = 5.0  # how long a shot waits for every camera's next frame
STATE_TIMEOUT_S = 5.0  # how long a hand-eye shot waits for a robot state newer than its frames
STILL_MM = 1.0  # the arm moved during a hand-eye shot when its EEF moved more than this...
STILL_DEG = 0.2  # ...or turned more than this


@dataclass(frozen=True)
class Shot:
    key: str  # NNN: the images' file stem and, for hand_eye, the pose's key
    corners: dict[str, int]  # camera -> board corners found
    paths: dict[str, Path]


def _stems(folder: Path) -> Iterator[str]:
    if folder.is_dir():
        yield from (p.stem for p in folder.iterdir() if p.is_file())


def next_number(images: Path, cameras: list[str], kind: str, poses: dict) -> int:
    """One past the highest shot number among the images (and poses) already there."""
    taken = [int(s) for c in cameras for s in _stems(images / c / kind) if s.isdigit()]
    taken += [int(k) for k in poses if str(k).isdigit()]
    return max(taken, default=-1) + 1


def read_poses(path: Path) -> dict:
    """The poses already captured (empty when there is no file); a malformed file is an error."""
    if not path.exists():
        return {}
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise CalibrationError(f"{path} is not valid YAML: {exc}; move it away to start a new one") from None
    if not isinstance(data, dict) or not isinstance(data.get("poses", {}), dict):
        raise CalibrationError(f"{path} holds no 'poses' mapping; move it away to start a new one")
    return dict(data.get("poses") or {})


def write_poses(path: Path, poses: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(
        "# the arm's EEF pose at each hand-eye shot (robot base frame, m, quaternion w x y z), by image stem\n"
        + yaml.safe_dump({"poses": poses}, sort_keys=True)
    )
    os.replace(tmp, path)


def _fresh_frames(driver, after_ns: int, timeout_s: float) -> dict[str, Frame]:
    """Every camera's first frame captured at or after ``after_ns``."""
    got: dict[str, Frame] = {}
    deadline = time.monotonic() + timeout_s
    while True:
        for name, frame in driver.grab(now_ns()).items():
            if name not in got and frame.stamp_ns >= after_ns:
                got[name] = frame
        missing = [n for n in driver.cameras if n not in got]
        if not missing:
            return got
        if time.monotonic() > deadline:
            raise CalibrationError(
                f"camera {', '.join(missing)}: no new frame within {timeout_s:g} s (unplugged? `viewscale check`)"
            )
        time.sleep(0.005)


def _moved(a, b) -> str | None:
    dp = 1000 * float(np.linalg.norm(np.asarray(a.eef_pos) - np.asarray(b.eef_pos)))
    R_a, R_b = (quat_wxyz_to_matrix(np.asarray(s.eef_quat_wxyz)) for s in (a, b))
    deg = float(np.degrees(np.linalg.norm(rotation_error(R_b, R_a))))
    if dp > STILL_MM or deg > STILL_DEG:
        return f"the arm moved {dp:.1f} mm and {deg:.2f} degrees during the shot: hold it still, and take it again"
    return None


class ArmPoses:
    """The newest ``robot/state`` on the bus, as the robot service publishes it."""

    def __init__(self, bus: Bus):
        self._cond = threading.Condition()
        self._latest: tuple[int, RobotState] | None = None  # (receive ns, state)
        bus.subscribe(topics.ROBOT_STATE, self._on_state)

    def _on_state(self, msg: RobotState, rx) -> None:
        with self._cond:
            self._latest = (rx.receive_ns, msg)
            self._cond.notify_all()

    def after(self, t_ns: int, timeout_s: float = STATE_TIMEOUT_S) -> RobotState:
        """The first state received at or after ``t_ns``."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._latest is not None and self._latest[0] >= t_ns, timeout_s):
                raise CalibrationError(
                    f"no robot/state on the bus within {timeout_s:g} s: run the router and the robot service "
                    "with this session file (hand_eye reads the arm's pose from it); on a bus with access "
                    "control, run capture as the operator user (VIEWSCALE_BUS__USER=operator "
                    "VIEWSCALE_BUS__PASSWORD_FILE=.../operator.password), which may hear robot/state"
                )
            return self._latest[1]


class Capture:
    """The open cameras (and, for hand_eye, the bus) of one capture session."""

    def __init__(
        self,
        config: str,
        images: Path,
        kind: str,
        board: BoardSpec,
        overrides: dict[str, list[str]] | None = None,
    ):
        if kind not in IMAGE_KINDS:
            raise CalibrationError(f"--kind {kind!r}: choose from {', '.join(IMAGE_KINDS)}")
        overrides = overrides or {}
        self.images, self.kind, self.board = Path(images), kind, board
        self.cameras = self.bus = self.arm = None
        if self.images.exists() and not self.images.is_dir():
            raise CalibrationError(f"--images {self.images} is a file: name a folder")
        cam_cfg = load_config(CameraConfig, config, overrides.get("camera", []), section="camera")
        try:
            rig = load_rig(cam_cfg.rig)
        except ConfigError:  # not calibrated yet, which is why we are here
            rig = stand_in_rig(cam_cfg)
            if rig is None:
                raise CalibrationError(
                    f"camera.rig {cam_cfg.rig!r} cannot be loaded, and the {cam_cfg.driver.type} driver names no "
                    "cameras of its own to open without it"
                ) from None
        self.poses_path = self.images / POSES_FILE
        self.poses: dict = {}
        if kind == "hand_eye":  # the robot service's bus: where its robot/state goes
            self.poses = read_poses(self.poses_path)
            robot_cfg = load_config(RobotConfig, config, overrides.get("robot", []), section="robot")
            self.bus = Bus(robot_cfg.bus)
            self.arm = ArmPoses(self.bus)
            try:
                self.arm.after(0)  # is the robot service there? (before any camera is opened)
            except BaseException:
                self.close()
                raise
        try:
            self.cameras = CAMERA_DRIVERS.build(cam_cfg.driver, rig=rig, width=cam_cfg.width, height=cam_cfg.height)
        except BaseException:
            self.close()
            raise
        self.names = list(self.cameras.cameras)
        self.number = next_number(self.images, self.names, kind, self.poses)

    def shot(self) -> Shot:
        """Take one shot: a new frame of every camera (and the arm's pose), saved."""
        t0 = now_ns()
        before = self.arm.after(t0) if self.arm is not None else None
        frames = _fresh_frames(self.cameras, now_ns(), FRAME_TIMEOUT_S)
        if self.arm is not None:
            after = self.arm.after(max(f.stamp_ns for f in frames.values()))
            moved = _moved(before, after)
            if moved:
                raise CalibrationError(moved)
        key = f"{self.number:03d}"
        corners, paths = {}, {}
        for name in self.names:
            bgr = cv2.cvtColor(frames[name].rgb, cv2.COLOR_RGB2BGR)
            corners[name] = len(detect(self.board, bgr).ids)
            folder = self.images / name / self.kind
            folder.mkdir(parents=True, exist_ok=True)
            paths[name] = folder / f"{key}.png"
            if not cv2.imwrite(str(paths[name]), bgr):
                raise CalibrationError(f"cannot write {paths[name]}")
        if self.arm is not None:
            self.poses[key] = {
                "position": [round(float(v), 6) for v in before.eef_pos],
                "quat_wxyz": [round(float(v), 7) for v in before.eef_quat_wxyz],
            }
            write_poses(self.poses_path, self.poses)
        self.number += 1
        return Shot(key, corners, paths)

    def describe(self, shot: Shot) -> str:
        seen = ", ".join(
            f"{n} {c}/{self.board.n_corners} corners" if c else f"{n} board not found" for n, c in shot.corners.items()
        )
        where = self.images / "*" / self.kind / f"{shot.key}.png"
        pose = ""
        if self.arm is not None:
            pose = f", EEF at ({', '.join(f'{v:.3f}' for v in self.poses[shot.key]['position'])}) m"
        return f"[{shot.key}] {seen}{pose} -> {where}"

    def close(self) -> None:
        if self.cameras is not None:
            self.cameras.close()
        if self.bus is not None:
            self.bus.close()

    def __enter__(self) -> Capture:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def next_command(images: Path, kind: str) -> str:
    how = {
        "intrinsics": "--board-pose board_pose.yaml (after the board shots) or --gripper-poses",
        "board": "--board-pose board_pose.yaml",
        "hand_eye": f"--gripper-poses {images / POSES_FILE}",
    }[kind]
    return f"viewscale calibrate rig --images {images} {how} --out deploy/rig-calibrated.yaml"


def run_capture(
    cap: Capture,
    count: int | None,
    every_s: float,
    lines: Callable[[], str] = sys.stdin.readline,
    say: Callable[[str], None] = print,
) -> list[Shot]:
    """Take shots: ``count`` of them ``every_s`` apart, or one per Enter until q or end of input."""
    shots: list[Shot] = []

    def take() -> None:
        try:
            shots.append(cap.shot())
            say(cap.describe(shots[-1]))
        except CalibrationError as exc:  # (one bad shot is said and skipped; the session goes on)
            say(f"shot not taken: {exc}")

    if count is not None:
        for i in range(count):
            if i:
                time.sleep(every_s)
            take()
        return shots
    say(f"cameras {', '.join(cap.names)}: Enter takes a shot, q and Enter ends")
    while True:
        line = lines()
        if not line or line.strip().lower() in ("q", "quit", "exit"):
            return shots
        take()
