"""The robot driver interface: what the robot service needs from any arm, real or simulated."""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod

from services.core.robot_types import EefDelta


class RobotDriver(ABC):
    """An arm with a parallel gripper driven by end-effector deltas at a fixed control rate.

    ``read()`` returns an object with the fields of ``RobotState`` (eef_pos, eef_quat_wxyz,
    joint_pos, joint_vel, gripper). ``apply()`` executes one tick's delta; a simulated driver
    advances physics by one control period, a real one sends the target and returns.
    """

    @abstractmethod
    def read(self): ...

    @abstractmethod
    def apply(self, action: EefDelta) -> None: ...

    def close(self) -> None:
        """Release the hardware (default: nothing to release)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def load_driver_class(spec: str) -> type[RobotDriver]:
    """``"package.module:ClassName"`` -> the class, checked to be a RobotDriver.

    This is how a lab plugs in its real arm: ``robot.driver: mylab.arms:FrankaDriver`` in
    deploy/real.yaml; nothing else changes.
    """
    module_name, sep, class_name = spec.partition(":")
    if not sep or not module_name or not class_name:
        raise ValueError(f"robot driver {spec!r} must look like 'package.module:ClassName'")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ValueError(f"robot driver module {module_name!r} cannot be imported: {exc}") from exc
    cls = getattr(module, class_name, None)
    if not (isinstance(cls, type) and issubclass(cls, RobotDriver)):
        raise ValueError(f"{spec!r} is not a RobotDriver subclass")
    return cls
