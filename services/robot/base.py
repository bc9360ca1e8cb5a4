"""The robot driver interface: what the robot service needs from any arm, real or simulated.

A robot driver is chosen by the robot service's ``driver`` config (``services.robot.config``,
through ``services.core.registry``): the sim arm (``type: sim``), the Universal Robots arm
(``type: ur``, ``services.robot.ur``) or a lab's own arm (``type: mylab.arms:MyArm``). Every driver
runs behind ``services.robot.safety``: ``apply`` only ever receives actions within the workspace
box and the speed caps, and never while the driver reports a fault.

Adding an arm (``services/robot/ur.py`` is the worked example)
---------------------------------------------------------------
1. Subclass ``RobotDriver`` and implement ``read`` (the arm now, as a ``RobotSnapshot``: EEF pose in
   the base frame, quaternion w-first, joints, gripper closure in [0, 1]) and ``apply`` (one tick's
   ``EefDelta``: send it and return; never block for the motion). Keep the SDK import inside
   ``from_config``, so a process that runs another driver never needs it (``UR.from_config``
   raises a ``ConfigError`` naming ``pip install ur-rtde`` when it is missing).
2. Give it a typed config: a frozen pydantic model (``services.core.config.Frozen``, one comment
   per field) with the address, rates, gripper and so on, and build the driver from it in
   ``from_config(cfg, *, control_hz)``; a connection that cannot be made raises ``ConnectionError``
   there, so the service exits with one line before it joins the bus.
3. Where the arm servos to a target it keeps (``UR`` integrates the deltas into a target pose),
   return that target's position from ``target_position``: the workspace box then bounds where
   the arm is going, not just where it is.
4. ``stop`` brings the arm to rest (``UR``: ``servoStop``); the safety layer calls it when commands
   stop coming and when a fault begins. ``fault`` says why the arm cannot move right now
   (``UR``: a protective or emergency stop, a safety or robot mode other than normal/running, a
   lost connection): while it is not empty the arm is stopped and sent nothing, and every tick's
   ``AppliedAction.fault`` carries it, so the recorder flags the episode and keeps it.
   ``close`` releases the hardware (``UR``: ``servoStop``, ``stopScript``, ``disconnect``).
5. Make it selectable, either way:
   - by import path, no registration: ``driver: {type: mylab.arms:MyArm, host: 10.0.0.2}``; a
     nested ``class Config(Frozen)`` on ``MyArm`` types the other keys (an unknown key is an error);
   - by name, in ``services/robot/config.py``: ``class MyArmConfig(DriverConfig)`` with
     ``type: Literal["myarm"] = "myarm"`` and its fields, then
     ``ROBOT_DRIVERS.register("myarm", "mylab.arms:MyArm", MyArmConfig)``
     (``URRobotConfig`` / ``"ur"`` is the example).
6. Test it against an in-test fake of the vendor SDK through the real safety layer and control
   loop (``tests/integration/test_robot_ur.py`` does this for ``ur-rtde``).
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
        """Commands stopped coming, or a fault began: bring the arm to rest (default: nothing
        beyond holding still)."""

    def fault(self) -> str:
        """Why the arm cannot move right now (a protective stop, a lost connection), '' when it
        can. While it is not empty the safety layer sends the driver nothing and flags every tick."""
        return ""

    def close(self) -> None:
        """Release the hardware (default: nothing to release)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
