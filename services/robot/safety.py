"""The safety layer: every robot driver, simulated or real, runs behind it.

Per control tick it takes the command the loop received (or none) and decides what the driver
executes, in this order:

0. a driver fault (``RobotDriver.fault``: a protective stop, a lost connection): when it begins,
   log it as an error and stop the arm (``RobotDriver.stop``); while it lasts send the driver
   nothing and report a hold carrying the fault (the loop puts it in ``AppliedAction.fault``, the
   recorder flags the episode); once it clears, commands move the arm again;
1. no fresh command: hold still (zero motion, the last gripper target; before any command, the
   gripper as it is: closed on an object stays closed); once no fresh command
   has come for ``command_timeout_s``, stop the arm (``RobotDriver.stop``) and keep holding
   until commands come again;
2. translation capped at ``max_speed / control_hz`` metres and rotation at
   ``max_angular_speed / control_hz`` radians per tick (the vector is scaled, its direction kept);
3. the workspace box: the translation is cut so that the position the arm is servoing to
   (``RobotDriver.target_position``, or the measured EEF where a driver keeps no target) stays
   inside ``workspace_lo``..``workspace_hi``, per axis; on an axis where the arm is outside the
   box it may only move towards it (at the capped speed: the arm is never pulled in);
4. the gripper target clamped to [0, 1].

What it returns is the action that really ran and the limits that changed it; the control loop
publishes exactly that on ``robot/applied``, so a demonstration records what the arm did, not
what was asked. The sim gets the same limits as hardware because it sits behind the same layer.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
from pydantic import Field, model_validator

from services.core.config import Frozen
from services.core.geometry import clip_norm
from services.core.robot_types import EefDelta, RobotSnapshot, kept_gripper
from services.robot.base import RobotDriver

log = logging.getLogger(__name__)

SPEED, ROTATION, WORKSPACE, GRIPPER = "speed", "rotation", "workspace", "gripper"
MAX_FAULT = 200  # characters of a fault kept on the wire (a session string is at most 256)


class SafetyConfig(Frozen):
    workspace_lo: tuple[float, float, float] = (0.15, -0.45, 0.0)  # EEF target box, base frame (m)
    workspace_hi: tuple[float, float, float] = (0.8, 0.45, 0.55)  # its upper corner
    max_speed: float = Field(0.6, gt=0)  # m/s: per-tick translation cap = max_speed / control_hz
    max_angular_speed: float = Field(3.0, gt=0)  # rad/s: per-tick rotation cap = max_angular_speed / control_hz
    command_timeout_s: float = Field(1.0, gt=0)  # no fresh command for this long: stop the arm (hold before)

    @model_validator(mode="after")
    def _box(self) -> SafetyConfig:
        if any(lo >= hi for lo, hi in zip(self.workspace_lo, self.workspace_hi)):
            raise ValueError(f"workspace_lo {self.workspace_lo} must be below workspace_hi {self.workspace_hi}")
        return self


@dataclass(frozen=True)
class Executed:
    """One tick's outcome: what the driver executed and why it differs from the command."""

    action: EefDelta  # what ran (base frame)
    stale: bool  # no fresh command: a hold
    limits: tuple[str, ...] = ()  # the limits that changed the command (speed, rotation, workspace, gripper)
    fault: str = ""  # why the arm could not move (the driver's fault); then nothing was sent to it


class Safety:
    """A RobotDriver behind the limits of ``SafetyConfig``; a context manager closing the driver."""

    def __init__(self, driver: RobotDriver, cfg: SafetyConfig, control_hz: float):
        self.driver = driver
        self.cfg = cfg
        self.max_dp = cfg.max_speed / control_hz
        self.max_drot = cfg.max_angular_speed / control_hz
        self._lo = np.asarray(cfg.workspace_lo, dtype=np.float64)
        self._hi = np.asarray(cfg.workspace_hi, dtype=np.float64)
        self._snapshot: RobotSnapshot | None = None
        # the gripper target a hold keeps: the last command's, or, before any, where the gripper is
        # (above 0.5: closed, as the teleop devices take it over); None until then
        self._gripper: float | None = None
        self._last_fresh = time.monotonic()
        self.stopped = False  # the arm was stopped for want of commands
        self.stops = 0  # times that happened
        self.fault = ""  # the driver's current fault ('' when the arm can move)
        self._outside = False  # the arm was outside the workspace box at the last command (warned once)
        self.faults = 0  # faults begun (each stopped the arm)

    def begin_episode(self) -> None:
        """A new episode (the sim's reset): the gripper target read again, the command timeout
        counted from now."""
        self._gripper = None
        self._snapshot = None
        self._last_fresh = time.monotonic()
        self.stopped = False

    def read(self) -> RobotSnapshot:
        self._snapshot = self.driver.read()
        return self._snapshot

    def limit(self, command: EefDelta) -> tuple[EefDelta, tuple[str, ...]]:
        """``command`` within the speed caps, the workspace box and the gripper range."""
        limits: list[str] = []
        dp = np.asarray(command.dp, dtype=np.float64)
        drot = np.asarray(command.drot, dtype=np.float64)
        if np.linalg.norm(dp) > self.max_dp:
            dp = clip_norm(dp, self.max_dp)
            limits.append(SPEED)
        if np.linalg.norm(drot) > self.max_drot:
            drot = clip_norm(drot, self.max_drot)
            limits.append(ROTATION)
        ref = self.driver.target_position()
        if ref is None:
            ref = (self._snapshot or self.read()).eef_pos
        ref = np.asarray(ref, dtype=np.float64)
        goal = ref + dp
        # per axis the goal may go anywhere in the box, and where the arm is outside it (jogged there
        # by hand, a box drawn tighter than where it rests) back towards it too: a clip into an
        # interval that holds ``ref`` never lengthens the step (before: into the box, so that any
        # command, a zero one too, jumped an arm outside it into the box in one tick at any speed)
        lo, hi = np.minimum(self._lo, ref), np.maximum(self._hi, ref)
        if np.any((goal < lo) | (goal > hi)):
            dp = np.clip(goal, lo, hi) - ref
            limits.append(WORKSPACE)
        outside = bool(np.any((ref < self._lo) | (ref > self._hi)))
        if outside and not self._outside:
            log.warning(
                "the arm is outside the workspace box (%s, box %s..%s): commands move it only towards the box",
                np.round(ref, 3).tolist(),
                list(self.cfg.workspace_lo),
                list(self.cfg.workspace_hi),
            )
        self._outside = outside
        gripper = min(max(float(command.gripper), 0.0), 1.0)
        if gripper != command.gripper:
            limits.append(GRIPPER)
        return EefDelta(dp, drot, gripper), tuple(limits)

    def apply(self, command: EefDelta | None) -> Executed:
        """Execute one tick: ``command`` within the limits, or a hold when it is None."""
        now = time.monotonic()
        fault = self.driver.fault()[:MAX_FAULT]
        if fault:
            return self._faulted(fault, command, now)
        if self.fault:
            log.warning("robot fault cleared (was: %s): commands move the arm again", self.fault)
            self.fault = ""
            self._last_fresh = now
        if command is None:
            if not self.stopped and now - self._last_fresh >= self.cfg.command_timeout_s:
                self.stopped = True
                self.stops += 1
                log.warning("no command for %.1f s: stopping the arm", now - self._last_fresh)
                self.driver.stop()
            hold = EefDelta.hold(self._held_gripper())
            self.driver.apply(hold)
            return Executed(hold, stale=True)
        if self.stopped:
            log.info("commands are back after %.1f s: moving again", now - self._last_fresh)
            self.stopped = False
        self._last_fresh = now
        action, limits = self.limit(command)
        self.driver.apply(action)
        self._gripper = action.gripper
        return Executed(action, stale=False, limits=limits)

    def _faulted(self, fault: str, command: EefDelta | None, now: float) -> Executed:
        if fault != self.fault:
            self.faults += 1
            log.error("robot fault: %s; the arm is stopped and gets no commands until it clears", fault)
            self.driver.stop()
        self.fault = fault
        if command is not None:
            self._last_fresh = now  # the teleop is there: no command timeout on top of the fault
        return Executed(EefDelta.hold(self._held_gripper()), stale=command is None, fault=fault)

    def _held_gripper(self) -> float:
        """What a hold commands the gripper: the last command's target; before any, where it is
        (before: open, so a robot service started with an object in the gripper dropped it)."""
        if self._gripper is None:
            self._gripper = kept_gripper((self._snapshot or self.read()).gripper)
        return self._gripper

    def close(self) -> None:
        self.driver.close()

    def __enter__(self) -> Safety:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
