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
import zlib
from pathlib import Path

import numpy as np

from services.core.config import ConfigError
from services.core.robot_types import EefDelta
from services.pb.sensors_pb2 import RobotState, TaskState
from services.policy.client import ChunkRunner, PolicyClient, PolicyError, State
from services.teleop.base import CameraFrame, TeleopDriver
from services.teleop.config import PolicyTeleopConfig

log = logging.getLogger(__name__)


class PolicyTeleop(TeleopDriver):
    def __init__(self, cfg: PolicyTeleopConfig):
        self.cfg = cfg
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
        self.episode_stats: dict[str, dict] = {}
        log.info(
            "policy %s at %s: views %s, %s",
            info.model_id,
            cfg.server,
            ",".join(self.cameras),
            "blocking (lockstep)" if cfg.blocking else "real time",
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
        }
        self.episode_stats[self.episode_id] = row
        if self.cfg.stats_file:
            with open(Path(self.cfg.stats_file), "a") as f:
                f.write(json.dumps(row) + "\n")

    def reset(self, task: str, episode_id: str = "") -> None:
        self._finish_episode()
        self.episode_id = episode_id
        self.first_error = None
        seed = self.cfg.seed if self.cfg.seed is not None else zlib.crc32(episode_id.encode()) * 1000
        self.runner = ChunkRunner(
            self.client,
            blocking=self.cfg.blocking,
            views=list(self.cameras),
            gamma=self.cfg.gamma,
            seed=seed,
            on_error=self._on_error,
        )

    def _on_error(self, exc: PolicyError) -> None:
        if self.first_error is None:
            self.first_error = str(exc)
        log.warning("GetAction failed in %s: %s (holding still)", self.episode_id, exc)

    def act(self, state: RobotState, task: TaskState | None, frames: dict[str, CameraFrame]) -> EefDelta:
        if not state.episode_id and not self.cfg.outside_episodes:
            # no episode is being recorded (an operator resetting the scene): hold still, ask nothing
            # (before: the policy drove a real arm from the teleop's start on, between episodes too)
            # the gripper kept as it is, closed on an object closed, as the devices and the safety
            # layer's holds keep it (before: the reading itself, a target where a gripper has no grip)
            return EefDelta(np.zeros(3), np.zeros(3), 1.0 if state.gripper > 0.5 else 0.0)
        if self.runner is None:
            self.reset("", state.episode_id)
        now = State(np.asarray(state.eef_pos), np.asarray(state.eef_quat_wxyz), state.gripper, state.header.stamp_ns)
        action, _fresh = self.runner.act(int(state.tick), {c: (f.jpeg, f.stamp_ns) for c, f in frames.items()}, now)
        return EefDelta(np.asarray(action[0:3]), np.asarray(action[3:6]), float(action[6]))

    def close(self) -> None:
        self._finish_episode()
        self.client.close()
