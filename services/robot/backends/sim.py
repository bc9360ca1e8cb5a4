"""The simulated arm: a RobotDriver over a shared MuJoCo ``SimWorld``."""

from __future__ import annotations

from services.core.robot_types import EefDelta
from services.robot.backends.base import RobotDriver


class SimRobotDriver(RobotDriver):
    def __init__(self, world):
        self.world = world  # sim.world.SimWorld, shared with the simulated cameras

    def read(self):
        return self.world.robot()

    def apply(self, action: EefDelta) -> None:
        self.world.step(action.dp, action.drot, action.gripper)
