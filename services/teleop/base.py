"""The teleop driver interface: anything that turns what the robot reports into EEF delta commands.

A teleop driver is chosen by the teleop service's ``driver`` config (``services.teleop.config``,
through ``services.core.registry``): the sim's scripted expert (``type: scripted``) or a lab's own
class (``type: package.module:Class``, with a nested ``Config`` for its settings).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

from services.core.robot_types import EefDelta
from services.pb.sensors_pb2 import RobotState, TaskState


class TeleopDriver(ABC):
    #: True when the driver needs the simulator's privileged TaskState (scripted experts).
    needs_task_state: bool = False

    @classmethod
    def from_config(cls, cfg: Any) -> TeleopDriver:
        """Build from the driver's typed config (None for a class without a Config)."""
        return cls(cfg)  # type: ignore[call-arg]

    @abstractmethod
    def reset(self, task: str) -> None:
        """A new episode of ``task`` begins."""

    @abstractmethod
    def act(self, state: RobotState, task: TaskState | None) -> EefDelta:
        """The command answering ``state`` (same tick)."""

    def close(self) -> None:
        """Release the device (default: nothing to release)."""
