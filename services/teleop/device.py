"""What the hand-held teleop devices share: the mapping to EEF deltas, the gripper toggle, and the
episode keys that drive the recorder.

A device (``keyboard.py``, ``spacemouse.py``) reads its input on its own thread and keeps a
*deflection*: translation and rotation, each (3,) in [-1, 1] along the robot base axes, zero when
its deadman says the operator let go. Every tick ``act`` turns it into the same command the
scripted expert sends (``sim/experts.py``, ``services/core/robot_types.EefDelta``)::

    dp   = clip_norm(speed * max_dp   * translation, max_dp)     # metres this tick, base frame
    drot = clip_norm(speed * max_drot * rotation,    max_drot)   # axis-angle this tick, R_next = Rot(drot) @ R
    gripper = the toggled target, 0 open or 1 closed

with ``max_dp`` 0.02 m and ``max_drot`` 0.1 rad by default: the expert's free-space step (0.4 m/s
at 20 Hz) and rotation cap. The gripper target starts from what the robot reports at the first
tick of an episode (above 0.5: closed), so taking over never snaps the gripper.

Episode keys post ``start``, ``stop`` (success or failure) or ``discard`` to a worker thread that
sends them through ``services.recorder.control`` on the teleop service's bus (the same requests
as ``viewscale episode``) and logs the recorder's answer; a slow STOP never stalls the device.
The device reads only ``RobotState``: it needs no task state and works on any robot.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable

import numpy as np

from services.core.bus import Bus
from services.core.geometry import clip_norm
from services.core.robot_types import EefDelta, kept_gripper
from services.pb.episode_pb2 import EpisodeReply
from services.pb.sensors_pb2 import RobotState, TaskState
from services.recorder.control import describe_reply, episode_control, episode_request
from services.teleop.base import CameraFrame, TeleopDriver
from services.teleop.config import DeviceTeleopConfig

log = logging.getLogger(__name__)

Clock = Callable[[], float]  # monotonic seconds

# What an episode key asks for. "start_or_stop": start when the recorder is idle, else stop as a success.
EPISODE_ACTIONS = ("start", "stop_success", "stop_failure", "discard", "start_or_stop")


def eef_delta(
    translation: np.ndarray, rotation: np.ndarray, speed: float, max_dp: float, max_drot: float, gripper: float
) -> EefDelta:
    """A deflection ((3,) each, nominally in [-1, 1], base frame) -> one tick's EEF delta, capped at
    ``max_dp`` metres and ``max_drot`` radians whatever the inputs."""
    t = np.clip(np.asarray(translation, dtype=np.float64), -1.0, 1.0)
    r = np.clip(np.asarray(rotation, dtype=np.float64), -1.0, 1.0)
    return EefDelta(
        clip_norm(speed * max_dp * t, max_dp),
        clip_norm(speed * max_drot * r, max_drot),
        float(np.clip(gripper, 0.0, 1.0)),
    )


class EpisodeKeys:
    """Episode commands from a device, sent to the recorder on a worker thread, one at a time."""

    def __init__(self, cfg: DeviceTeleopConfig):
        self.cfg = cfg
        self.bus: Bus | None = None
        self.replies: list[tuple[str, EpisodeReply]] = []  # (action, reply) of every answered request
        self._queue: queue.SimpleQueue[str | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="teleop-episode-keys", daemon=True)
        self._thread.start()

    def post(self, action: str) -> None:
        if action not in EPISODE_ACTIONS:
            raise ValueError(f"unknown episode action {action!r}")
        self._queue.put(action)

    def _send(self, action: str, **fields) -> EpisodeReply:
        req = episode_request(action, task=self.cfg.task, rig=self.cfg.rig, control_hz=self.cfg.control_hz, **fields)
        return episode_control(self.bus, req, self.cfg.episode_timeout_s)

    def _handle(self, action: str) -> None:
        if self.bus is None:
            log.warning(
                "episode key %s ignored: the driver is not attached to a bus (run it in the teleop service)", action
            )
            return
        if action == "start_or_stop":
            status = self._send("status")
            action = "stop_success" if status.ok and status.recording else "start"
        if action == "start":
            reply = self._send("start")
        elif action == "discard":
            reply = self._send("discard")
        else:
            reply = self._send("stop", success=action == "stop_success")
        self.replies.append((action, reply))
        if reply.ok:  # (a start's warnings, as `viewscale episode start` prints them: a warning here too)
            level = logging.WARNING if reply.recording and reply.meta.flags else logging.INFO
            log.log(level, "episode key %s: %s", action, describe_reply(action, reply))
        else:
            log.warning("episode key %s refused by the recorder: %s", action, reply.error)

    def _run(self) -> None:
        while (action := self._queue.get()) is not None:
            try:
                self._handle(action)
            except (TimeoutError, RuntimeError, ConnectionError) as exc:
                log.warning("episode key %s: no answer from the recorder: %s", action, exc)

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join(timeout=self.cfg.episode_timeout_s + 5.0)


class DeviceTeleop(TeleopDriver):
    """Base of the hand-held devices: subclasses read their device and implement ``deflection``."""

    needs_task_state = False  # only RobotState: the teleop has no robot-side privileges

    def __init__(self, cfg: DeviceTeleopConfig, clock: Clock = time.monotonic):
        self.cfg = cfg
        self.clock = clock
        self.speed = cfg.speed
        self.episodes = EpisodeKeys(cfg)
        self._lock = threading.Lock()
        self._gripper: float | None = None  # target; None until the episode's first state says where it is
        self._toggles = 0  # gripper toggles not yet applied

    @classmethod
    def from_config(cls, cfg: DeviceTeleopConfig, **context) -> DeviceTeleop:
        return cls(cfg, **context)

    def deflection(self, now: float) -> tuple[np.ndarray, np.ndarray]:
        """(translation (3,), rotation (3,)) in [-1, 1] along the base axes at ``now``; zeros when idle."""
        raise NotImplementedError

    def toggle_gripper(self) -> None:
        with self._lock:
            self._toggles += 1

    def attach(self, bus: Bus) -> None:
        self.episodes.bus = bus

    def reset(self, task: str, episode_id: str = "") -> None:
        with self._lock:
            self._gripper = None
            self._toggles = 0

    def act(self, state: RobotState, task: TaskState | None, frames: dict[str, CameraFrame]) -> EefDelta:
        translation, rotation = self.deflection(self.clock())
        with self._lock:
            if self._gripper is None:
                self._gripper = kept_gripper(state.gripper)
            if self._toggles % 2:
                self._gripper = 1.0 - self._gripper
            self._toggles = 0
            gripper = self._gripper
        return eef_delta(translation, rotation, self.speed, self.cfg.max_dp, self.cfg.max_drot, gripper)

    def close(self) -> None:
        self.episodes.close()
