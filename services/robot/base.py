"""The robot driver interface: what the robot service needs from any arm, real or simulated.

A robot driver is chosen by the robot service's ``driver`` config (``services.robot.config``,
through ``services.core.registry``): the sim arm (``type: sim``) or a lab's own arm
(``type: mylab.arms:MyArm``). To add an arm, subclass ``RobotDriver``, give it a nested
``Config`` (a frozen pydantic model with its settings: address, gripper, ...), and implement
``read`` and ``apply``; ``stop``, ``target_position`` and ``close`` have safe defaults. Every
driver runs behind ``services.robot.safety``: ``apply`` only ever receives actions within the
workspace box and the speed caps.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import numpy as np

from services.core.robot_types import EefDelta, RobotSnapshot


class RobotDriver(ABC):
    """An arm with a parallel gripper driven by end-effector deltas at a fixed control rate.

    ``read()`` returns the arm's ``RobotSnapshot``. ``apply()`` executes one tick's delta; a
    simulated driver advances physics by one control period, a real one sends the target and
    returns.
    """

    @classmethod
    def from_config(cls, cfg: Any, *, control_hz: float) -> RobotDriver:
        """Build from the driver's typed config (None for a class without a Config)."""
        return cls(cfg, control_hz=control_hz)  # type: ignore[call-arg]

    @abstractmethod
    def read(self) -> RobotSnapshot: ...

    @abstractmethod
    def apply(self, action: EefDelta) -> None: ...

    def target_position(self) -> np.ndarray | None:
        """(3,) the position the arm is servoing to, if the driver keeps one (the safety layer
        keeps it inside the workspace); None: the measured EEF position is used instead."""
        return None

    def stop(self) -> None:
        """Commands stopped coming: bring the arm to rest (default: nothing beyond holding still)."""

    def close(self) -> None:
        """Release the hardware (default: nothing to release)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
