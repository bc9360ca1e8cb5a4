"""A trained policy as the teleop driver: the robot side of ``Policy.GetAction``.

    teleop:
      driver: {type: policy, server: 127.0.0.1:50051, views: [F, FL, FR]}

Each tick it hands the tick's frames of its cameras and the robot state to a ``ChunkRunner``
(services/policy/client.py), which executes the policy's action chunks one action per tick,
asks for the next chunk ahead of time, and holds still when none has come (an underrun). In a
lockstep session (``blocking: true``) it waits for the chunk instead. The same driver drives the
sim and a real arm: it needs nothing but the cameras and the robot state. It drives only while an
episode is recorded (states that name one); between episodes it holds the arm still.

Per episode it keeps the runner's statistics (requests, latency, underruns, stale actions,
degraded answers) and, with ``stats_file``, appends them as one JSON line when the episode ends.
"""

from __future__ import annotations

import json
import logging
import threading
import time
import zlib
from pathlib import Path

import numpy as np

from services.core import topics
from services.core.action_spaces import needs_calibration
from services.core.config import ConfigError
from services.core.rig import Camera, served_camera_gap
from services.core.robot_types import EefDelta, kept_gripper
from services.core.throttle import Throttle
from services.pb.sensors_pb2 import RobotState, TaskState
from services.policy.client import ChunkRunner, PolicyClient, PolicyError, State
from services.teleop.base import CameraFrame, TeleopDriver
from services.teleop.config import PolicyTeleopConfig

log = logging.getLogger(__name__)


class PolicyTeleop(TeleopDriver):
    def __init__(self, cfg: PolicyTeleopConfig):
        self.cfg = cfg
        self._stopping = threading.Event()  # the service is stopping: a lockstep act waits no longer
        try:
            tls_ca = Path(cfg.tls_ca).read_bytes() if cfg.tls_ca else None
        except OSError as exc:
            raise ConfigError(f"teleop driver policy: tls_ca {cfg.tls_ca}: {exc.strerror}") from None
        try:  # (the service's one error line, as a camera or arm that cannot be reached; before: a traceback)
            self.client = PolicyClient(
                cfg.server,
                session_id=f"teleop-{id(self):x}",
                token=cfg.token,
                tls_ca=tls_ca,
                timeout_s=cfg.timeout_s,
                connect_timeout_s=cfg.connect_timeout_s,
            )
        except PolicyError as exc:
            raise ConnectionError(f"teleop driver policy: {exc}") from None
        except ValueError as exc:  # a setting the client refuses: a tls_ca file that holds no certificate
            raise ConfigError(f"teleop driver policy: {exc} (tls_ca {cfg.tls_ca})") from None
        info = self.client.info
        self.cameras = tuple(cfg.views or info.default_views)
        known = {c.name for c in info.cameras}
        unknown = [c for c in self.cameras if c not in known]
        if unknown:
            self.client.close()
            raise ConfigError(
                f"teleop driver policy: views {', '.join(unknown)}: the policy server at {cfg.server} knows no such "
                f"camera ({', '.join(sorted(known))})"
            )
        self.runner: ChunkRunner | None = None
        self.episode_id = ""
        self.first_error: str | None = None
        self.refused: str | None = None  # why it did not drive in this episode (None: it drove)
        self.episode_stats: dict[str, dict] = {}
        # the cameras as the policy server computes with them, and as they publish themselves
        self._served = {c.name: c for c in info.cameras}
        self._geometry = needs_calibration(info.action_space, info.state_frame)
        self._live: dict[str, list] = {c: [None, None, 0] for c in self.cameras}  # [calibration, pose, version]
        self._moved: dict[str, str] = {}  # camera -> how its published calibration differs from the server's
        self._checked: dict[str, int] = {}  # camera -> the version of its messages last checked
        self._unheard_said = False  # a camera whose calibration never came was logged
        self._waited_said = False  # the wait for the cameras' calibration was logged
        self._wait_until: float | None = None  # until when it waits for them (set at its first drive)
        self._errors = Throttle(log)  # failed GetActions
        self._lock = threading.Lock()
        log.info(
            "policy %s at %s: views %s, %s",
            info.model_id,
            cfg.server,
            ",".join(self.cameras),
            "blocking (lockstep)" if cfg.blocking else "real time",
        )

    def attach(self, bus) -> None:
        """Watch the cameras' published calibration and pose: one that differs from the server's (a
        camera moved and recalibrated since training, a server started with another rig) would turn
        the policy's camera-frame actions the wrong way."""
        for cam in self.cameras:
            for i, topic in enumerate((topics.camera_calibration(cam), topics.camera_pose(cam))):
                bus.subscribe(topic, lambda msg, rx, c=cam, i=i: self._on_camera(c, i, msg))

    def _on_camera(self, cam: str, i: int, msg) -> None:  # (zenoh threads: store only)
        with self._lock:
            self._live[cam][i] = msg
            self._live[cam][2] += 1

    def _check_cameras(self) -> None:
        """Compare each camera's newest published calibration and pose with the server's (when they
        changed), logging what starts or stops differing."""
        with self._lock:
            live = {c: tuple(m) for c, m in self._live.items()}
        for cam, (calib, pose, version) in live.items():
            if calib is None or pose is None or self._checked.get(cam) == version:
                continue
            self._checked[cam] = version
            try:
                camera, K = Camera.from_msgs(calib, pose)
            except (ValueError, ZeroDivisionError) as exc:
                log.warning("camera %s: unreadable calibration (%s): not checked against the policy server's", cam, exc)
                continue
            gap = served_camera_gap(self._served[cam], camera, K, (int(calib.width), int(calib.height)))
            before = self._moved.pop(cam, None)
            if gap:
                self._moved[cam] = gap
                if gap != before:
                    log.log(
                        logging.ERROR if self._geometry else logging.WARNING,
                        "camera %s publishes a calibration that differs from the policy server's (%s)%s",
                        cam,
                        gap,
                        ": the policy holds the arm still" if self._geometry else "",
                    )
            elif before:
                log.info("camera %s now matches the policy server's calibration", cam)

    def _waiting_for_calibration(self) -> bool:
        """Whether a camera-space policy still waits for a view's calibration and pose (for at most
        ``calibration_wait_s`` from its first tick that would drive, so that cameras started after
        the teleop are waited for too; before, it drove unchecked until they came). Past the wait
        it drives, and the cameras never heard are logged once."""
        if not self._geometry or self._unheard_said:
            return False
        unheard = sorted(c for c in self.cameras if c not in self._checked)
        if not unheard:
            return False
        if self._wait_until is None:
            self._wait_until = time.monotonic() + self.cfg.calibration_wait_s
        if time.monotonic() < self._wait_until:
            if not self._waited_said:
                self._waited_said = True
                log.info("holding still until camera %s publishes its calibration and pose", ", ".join(unheard))
            return True
        self._unheard_said = True  # (a camera service always publishes them: a bus that passes the images only?)
        log.warning(
            "no calibration and pose heard from camera %s in %g s: it is not checked against the policy "
            "server's (does this user hear camera/*/calibration and camera/*/pose?)",
            ", ".join(unheard),
            self.cfg.calibration_wait_s,
        )
        return False

    def _moved_cameras(self) -> str | None:
        """Why the policy must not drive: cameras whose published calibration differs from the
        server's, for a policy whose actions or states are in the camera frame."""
        self._check_cameras()
        if not self._moved or not self._geometry:
            return None
        return (
            "camera "
            + "; ".join(f"{c}: {g}" for c, g in sorted(self._moved.items()))
            + " from the calibration the policy server computes camera-frame actions with: they would move the "
            "arm the wrong way. Serve with the cameras' rig file (viewscale serve --rig ...), or recalibrate"
        )

    def _finish_episode(self) -> None:
        if self.runner is None or not self.episode_id:
            return
        s = self.runner.stats
        lat = sorted(s.latency_s)
        row = {
            "episode_id": self.episode_id,
            "requests": s.requests,
            "failed": s.failed,
            "degraded": s.degraded,
            "underruns": s.underruns,
            "stale_dropped": s.stale_dropped,
            "latency_ms": [round(x * 1e3, 3) for x in lat],
            "first_error": self.first_error,  # why the first failed GetAction failed (None: none did)
            "refused": self.refused,  # why it held the arm still instead of driving (None: it drove)
        }
        self.episode_stats[self.episode_id] = row
        if self.cfg.stats_file:
            with open(Path(self.cfg.stats_file), "a") as f:
                f.write(json.dumps(row) + "\n")

    def reset(self, task: str, episode_id: str = "") -> None:
        self._finish_episode()
        self.episode_id = episode_id
        self.first_error = None
        self.refused = None
        seed = self.cfg.seed if self.cfg.seed is not None else zlib.crc32(episode_id.encode()) * 1000
        self.runner = ChunkRunner(
            self.client,
            blocking=self.cfg.blocking,
            views=list(self.cameras),
            gamma=self.cfg.gamma,
            seed=seed,
            on_error=self._on_error,
            cancel=self._stopping,
        )

    def interrupt(self) -> None:
        self._stopping.set()

    def _on_error(self, exc: PolicyError) -> None:
        if self.first_error is None:
            self.first_error = str(exc)
        # the same failure at every tick: logged once, then once every 5 s with how many it stands for
        # (before: a line per tick, 20 a second while a server refused every request)
        self._errors(logging.WARNING, f"GetAction failed in {self.episode_id}: {exc} (holding still)")

    def _holds_still(self, state: RobotState) -> bool:
        """Whether this tick is a hold, asking the server nothing: no episode is being recorded (an
        operator resetting the scene; before: the policy drove a real arm from the teleop's start
        on, between episodes too), a camera-space policy's camera is placed elsewhere than the
        server has it (before: it drove with the server's calibration), or it still waits for the
        cameras' calibration."""
        if not state.episode_id and not self.cfg.outside_episodes:
            return True
        if why := self._moved_cameras():
            self.refused = self.refused or why  # (logged once, as it began: _check_cameras)
            return True
        return self._waiting_for_calibration()

    def act(self, state: RobotState, task: TaskState | None, frames: dict[str, CameraFrame]) -> EefDelta:
        if self._holds_still(state):
            # the gripper kept as it is, as the devices and the safety layer's holds keep it (before:
            # the reading itself, a target where a gripper has no grip)
            return EefDelta.hold(kept_gripper(state.gripper))
        if self.runner is None:
            self.reset("", state.episode_id)
        now = State(np.asarray(state.eef_pos), np.asarray(state.eef_quat_wxyz), state.gripper, state.header.stamp_ns)
        action, _fresh = self.runner.act(int(state.tick), {c: (f.jpeg, f.stamp_ns) for c, f in frames.items()}, now)
        return EefDelta(np.asarray(action[0:3]), np.asarray(action[3:6]), float(action[6]))

    def close(self) -> None:
        self._finish_episode()
        self.client.close()
