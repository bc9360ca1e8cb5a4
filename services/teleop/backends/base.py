"""Teleop sources: anything that turns what the robot reports into EEF delta commands."""

from __future__ import annotations

from abc import ABC, abstractmethod

from services.pb.sensors_pb2 import RobotState, TaskState
from services.core.robot_types import EefDelta


class TeleopSource(ABC):
    #: True when the source needs the simulator's privileged TaskState (scripted experts).
    needs_task_state: bool = False

    @abstractmethod
    def reset(self, task: str) -> None:
        """A new episode of ``task`` begins."""

    @abstractmethod
    def act(self, state: RobotState, task: TaskState | None) -> EefDelta:
        """The command answering ``state`` (same tick)."""

    def close(self) -> None:
        """Release the device (default: nothing to release)."""
