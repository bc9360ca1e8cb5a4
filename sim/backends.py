"""The sim's drivers behind the hardware interfaces: cameras, arm, and the scripted expert.

``SimCamera`` and ``SimRobot`` share one ``SimWorld`` in the sim service (rendering in lockstep
with physics); built on their own by the camera or robot service (``type: sim``), each opens a
world of its own. ``ScriptedTeleop`` runs the scripted experts in the teleop process from the
sim's privileged task state; it never loads MuJoCo (only the drivers that simulate import
``sim.world``, when they build their world).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from services.camera.base import CameraDriver, Frame
from services.core.rig import Camera, Rig, load_rig
from services.core.robot_types import EefDelta, RobotSnapshot, objects_from_msg, snapshot_from_msg
from services.pb.sensors_pb2 import RobotState, TaskState
from services.robot.base import RobotDriver
from services.teleop.base import TeleopDriver
from sim.experts import make_expert

if TYPE_CHECKING:
    from services.camera.config import SimCameraConfig
    from services.robot.config import SimRobotConfig
    from sim.world import SimWorld


class SimCamera(CameraDriver):
    """The rig's cameras rendered from a ``SimWorld``; its scene holds one MuJoCo camera per rig camera."""

    def __init__(self, world: SimWorld, width: int, height: int):
        self.world = world
        self._size = (width, height)

    @classmethod
    def from_config(cls, cfg: SimCameraConfig, *, rig: Rig, width: int, height: int) -> SimCamera:
        from sim.world import SimWorld  # MuJoCo: only for the drivers that simulate

        world = SimWorld(cfg.task, rig, width, height)
        world.reset(cfg.seed)
        return cls(world, width, height)

    @property
    def cameras(self) -> dict[str, Camera]:
        return self.world.rig.cameras

    @property
    def size(self) -> tuple[int, int]:
        return self._size

    def grab(self, stamp_ns: int) -> dict[str, Frame]:
        # In sim the capture time is the simulated instant all cameras share.
        return {name: Frame(rgb, stamp_ns) for name, rgb in self.world.render().items()}

    def close(self) -> None:
        self.world.close()


class SimRobot(RobotDriver):
    """The simulated arm of a ``SimWorld`` (shared with the simulated cameras in the sim service)."""

    def __init__(self, world: SimWorld):
        self.world = world

    @classmethod
    def from_config(cls, cfg: SimRobotConfig, *, control_hz: float) -> SimRobot:
        from sim.world import SimWorld  # MuJoCo: only for the drivers that simulate

        world = SimWorld(cfg.task, load_rig("front"), control_hz=control_hz)
        world.reset(cfg.seed)
        return cls(world)

    def read(self) -> RobotSnapshot:
        return self.world.robot()

    def apply(self, action: EefDelta) -> None:
        self.world.step(action.dp, action.drot, action.gripper)

    def target_position(self) -> np.ndarray:
        return self.world.target()[0]


class ScriptedTeleop(TeleopDriver):
    """The scripted experts (``sim.experts``) as a teleop driver: they read the sim's task state."""

    needs_task_state = True

    def __init__(self, cfg=None):
        self._expert = None
        self._task = ""

    def reset(self, task: str, episode_id: str = "") -> None:
        if task != self._task or self._expert is None:
            self._expert = make_expert(task)
            self._task = task
        self._expert.reset()

    def act(self, state: RobotState, task: TaskState | None, frames=None) -> EefDelta:
        if task is None:
            raise ValueError("the scripted expert needs the task state of the same tick")
        if self._expert is None or task.task != self._task:
            self.reset(task.task)
        dp, drot, gripper = self._expert.act(snapshot_from_msg(state), objects_from_msg(task))
        return EefDelta(np.asarray(dp, dtype=np.float64), np.asarray(drot, dtype=np.float64), float(gripper))
