"""Scripted experts: phase machines that steer the EEF through waypoints placed on the objects.

An expert sees only what goes over the wire -- the ``RobotSnapshot`` and the privileged object
poses of ``TaskState`` -- and returns one EEF delta action per 20 Hz tick. It knows the task's
geometry (object sizes, from ``sim.tasks``) the way a human demonstrator does, never MuJoCo.

Motion is a proportional step towards the phase's goal, measured from the *actual* EEF pose:
``dp = clip(GAIN * (goal - eef), speed)`` and ``drot = clip(GAIN * log(R_goal R^T), ...)``.
A gain below one keeps the world's integrated target from overshooting while the arm lags it.
The gripper stays pointing down; only its yaw turns, to the grasp yaw of the object (a cube
face pair, the nut's handle). Each phase has a tick budget; a phase that overruns it, or a
grasp that comes up empty, starts the attempt again from the approach.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod

import numpy as np

from services.core.geometry import (
    clip_norm,
    matrix_to_rotvec,
    nearest_yaw,
    quat_wxyz_to_matrix,
    quat_yaw,
    rot_z,
)
from services.core.robot_types import ObjectPose, RobotSnapshot
from sim.tasks import (
    CAN_HALF_HEIGHT,
    CUBE_HALF,
    NUT_GRASP_OFFSET,
    NUT_HALF_THICK,
    PEG_HEIGHT,
    TASKS,
)

Action = tuple[np.ndarray, np.ndarray, float]

GAIN = 0.5  # fraction of the remaining error commanded per tick
SPEED = 0.02  # m per tick in free space (0.4 m/s at 20 Hz)
SLOW = 0.01  # m per tick near contact
MAX_ROT = 0.1  # rad per tick
R_DOWN = np.diag([1.0, -1.0, -1.0])  # EEF pointing down at yaw 0 (sim.scene.R_DOWN)


class Expert(ABC):
    @abstractmethod
    def reset(self) -> None:
        """Forget the episode in progress."""

    @abstractmethod
    def act(self, robot: RobotSnapshot, objects: dict[str, ObjectPose]) -> Action:
        """(dp (3,), drot (3,), gripper) for the next tick."""


class _Scripted(Expert):
    first_phase = "approach"
    budgets: dict[str, int] = {}  # phase -> ticks before the attempt restarts

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.phase = self.first_phase
        self.phase_ticks = 0
        self.yaw: float | None = None  # grasp yaw, fixed when an approach starts
        self.attempts = 1

    def _go(self, phase: str) -> None:
        self.phase, self.phase_ticks = phase, 0

    def _restart(self) -> None:
        self.attempts += 1
        self.yaw = None
        self._go("recover")

    def _move(
        self, robot: RobotSnapshot, goal: np.ndarray, gripper: float, speed: float = SPEED
    ) -> tuple[Action, float, float]:
        """Action towards (goal, pointing down at self.yaw) and the remaining (pos, rot) errors."""
        yaw = quat_yaw(robot.eef_quat_wxyz) if self.yaw is None else self.yaw
        err_p = np.asarray(goal, dtype=np.float64) - robot.eef_pos
        err_r = matrix_to_rotvec(rot_z(yaw) @ R_DOWN @ quat_wxyz_to_matrix(robot.eef_quat_wxyz).T)
        dp = clip_norm(GAIN * err_p, speed)
        drot = clip_norm(GAIN * err_r, MAX_ROT)
        return (dp, drot, float(gripper)), float(np.linalg.norm(err_p)), float(np.linalg.norm(err_r))

    def act(self, robot: RobotSnapshot, objects: dict[str, ObjectPose]) -> Action:
        self.phase_ticks += 1
        budget = self.budgets.get(self.phase)
        if budget is not None and self.phase_ticks > budget:
            self._restart()
        return self._act(robot, objects)

    def _recover(self, robot: RobotSnapshot, height: float) -> Action:
        """Open and rise straight up, then approach again."""
        goal = np.array([robot.eef_pos[0], robot.eef_pos[1], height])
        action, ep, _ = self._move(robot, goal, 0.0)
        if ep < 0.02 and robot.gripper < 0.1:
            self._go("approach")
        return action

    def _release_and_retreat(self, robot: RobotSnapshot, height: float) -> Action:
        """Phase "release": open in place; then ("retreat") rise to ``height``, gripper open."""
        if self.phase == "release":
            action, _, _ = self._move(robot, robot.eef_pos.copy(), 0.0)
            if robot.gripper < 0.2:
                self._go("retreat")
            return action
        action, _, _ = self._move(robot, np.array([robot.eef_pos[0], robot.eef_pos[1], height]), 0.0)
        return action

    @abstractmethod
    def _act(self, robot: RobotSnapshot, objects: dict[str, ObjectPose]) -> Action: ...


class LiftExpert(_Scripted):
    """Above the cube, down, close, up."""

    budgets = {"approach": 60, "descend": 30, "grasp": 20, "lift": 60}
    hover = 0.08
    lift_to = 0.15

    def _act(self, robot, objects):
        cube = objects["cube"]
        if self.phase == "recover":
            return self._recover(robot, CUBE_HALF + self.hover)
        if self.yaw is None:
            # Fingers close along the EEF y axis: any yaw equal to a cube face's modulo 90 deg.
            self.yaw = nearest_yaw(quat_yaw(cube.quat_wxyz), quat_yaw(robot.eef_quat_wxyz), math.pi / 2)
        if self.phase == "approach":
            action, ep, er = self._move(robot, cube.pos + [0.0, 0.0, self.hover], 0.0)
            if ep < 0.01 and er < 0.05:
                self._go("descend")
            return action
        if self.phase == "descend":
            goal = np.array([cube.pos[0], cube.pos[1], CUBE_HALF])
            action, ep, er = self._move(robot, goal, 0.0, SLOW)
            if ep < 0.005 and er < 0.05:
                self._go("grasp")
            return action
        if self.phase == "grasp":
            action, _, _ = self._move(robot, np.array([cube.pos[0], cube.pos[1], CUBE_HALF]), 1.0, SLOW)
            if self.phase_ticks >= 6:
                self._go("lift")
            return action
        # lift: hold the cube up; an empty or slipped grasp starts over
        action, _, _ = self._move(robot, np.array([robot.eef_pos[0], robot.eef_pos[1], self.lift_to]), 1.0)
        if robot.gripper > 0.95 or robot.eef_pos[2] - cube.pos[2] > 0.04:
            self._restart()
        return action


class CanExpert(_Scripted):
    """Pick the can at its lower half, carry it over the bin, lower it in, let go, rise."""

    budgets = {"approach": 60, "descend": 30, "grasp": 20, "lift": 40, "carry": 60, "lower": 40, "release": 20}
    hover = 0.17  # EEF height over the table while approaching
    grip_z = CAN_HALF_HEIGHT - 0.02  # EEF height at the grasp: pads cover the can's lower 8 cm
    carry_z = 0.22
    drop_z = 0.08  # EEF height at release: the can's bottom ~3 cm above the bin floor

    def _act(self, robot, objects):
        can, bin_ = objects["can"], objects["bin"]
        if self.phase == "recover":
            return self._recover(robot, self.hover)
        if self.yaw is None:
            self.yaw = quat_yaw(robot.eef_quat_wxyz)
        if self.phase == "approach":
            action, ep, er = self._move(robot, np.array([can.pos[0], can.pos[1], self.hover]), 0.0)
            if ep < 0.01 and er < 0.05:
                self._go("descend")
            return action
        if self.phase == "descend":
            goal = np.array([can.pos[0], can.pos[1], self.grip_z])
            action, ep, _ = self._move(robot, goal, 0.0, SLOW * 1.5)
            if ep < 0.006:
                self._go("grasp")
            return action
        if self.phase == "grasp":
            action, _, _ = self._move(robot, np.array([can.pos[0], can.pos[1], self.grip_z]), 1.0, SLOW)
            if self.phase_ticks >= 6:
                self._go("lift")
            return action
        held = robot.gripper < 0.95 and np.linalg.norm(can.pos[:2] - robot.eef_pos[:2]) < 0.04
        if self.phase in ("lift", "carry", "lower") and not held:
            self._restart()
            return self._recover(robot, self.hover)
        # Put the can's centre (not the EEF) over the bin centre.
        offset = robot.eef_pos[:2] - can.pos[:2]
        over_bin = bin_.pos[:2] + offset
        if self.phase == "lift":
            goal = np.array([robot.eef_pos[0], robot.eef_pos[1], self.carry_z])
            action, ep, _ = self._move(robot, goal, 1.0)
            if robot.eef_pos[2] > self.carry_z - 0.05:
                self._go("carry")
            return action
        if self.phase == "carry":
            action, _, _ = self._move(robot, np.array([*over_bin, self.carry_z]), 1.0)
            if np.linalg.norm(can.pos[:2] - bin_.pos[:2]) < 0.02:
                self._go("lower")
            return action
        if self.phase == "lower":
            action, ep, _ = self._move(robot, np.array([*over_bin, self.drop_z]), 1.0)
            if ep < 0.01:
                self._go("release")
            return action
        return self._release_and_retreat(robot, self.carry_z)


class SquareExpert(_Scripted):
    """Grasp the nut's handle, lift it clear of the peg, centre its hole over the peg, lower it
    down the peg, let go."""

    budgets = {"approach": 60, "descend": 30, "grasp": 20, "lift": 40, "align": 80, "insert": 60, "release": 20}
    hover = 0.08
    carry_z = PEG_HEIGHT + 0.08  # EEF height while carrying: the nut hangs clear of the peg top
    insert_z = 0.03

    def _act(self, robot, objects):
        nut, peg = objects["nut"], objects["peg"]
        if self.phase == "recover":
            return self._recover(robot, self.hover + NUT_HALF_THICK)
        R_nut = quat_wxyz_to_matrix(nut.quat_wxyz)
        handle = nut.pos + R_nut @ np.array([NUT_GRASP_OFFSET, 0.0, 0.0])
        if self.yaw is None:
            # Fingers close across the handle: EEF yaw equal to the nut's modulo 180 deg.
            self.yaw = nearest_yaw(quat_yaw(nut.quat_wxyz), quat_yaw(robot.eef_quat_wxyz), math.pi)
        grip_z = max(handle[2], 0.015)
        if self.phase == "approach":
            action, ep, er = self._move(robot, np.array([handle[0], handle[1], grip_z + self.hover]), 0.0)
            if ep < 0.008 and er < 0.04:
                self._go("descend")
            return action
        if self.phase == "descend":
            action, ep, er = self._move(robot, np.array([handle[0], handle[1], grip_z]), 0.0, SLOW)
            if ep < 0.005 and er < 0.04:
                self._go("grasp")
            return action
        if self.phase == "grasp":
            action, _, _ = self._move(robot, np.array([handle[0], handle[1], grip_z]), 1.0, SLOW)
            if self.phase_ticks >= 6:
                self._go("lift")
            return action
        held = robot.gripper < 0.95 and np.linalg.norm(handle[:2] - robot.eef_pos[:2]) < 0.03
        if self.phase in ("lift", "align", "insert") and not held:
            self._restart()
            return self._recover(robot, self.hover + NUT_HALF_THICK)
        # Closed loop on the nut itself: move the EEF by the nut-to-peg error.
        to_peg = peg.pos[:2] - nut.pos[:2]
        if self.phase == "lift":
            action, _, _ = self._move(robot, np.array([robot.eef_pos[0], robot.eef_pos[1], self.carry_z]), 1.0)
            if robot.eef_pos[2] > self.carry_z - 0.01:
                self._go("align")
            return action
        if self.phase == "align":
            goal = np.array([*(robot.eef_pos[:2] + to_peg), self.carry_z])
            action, _, _ = self._move(robot, goal, 1.0)
            if np.linalg.norm(to_peg) < 0.003 and np.linalg.norm(robot.joint_vel) < 0.05:
                self._go("insert")
            return action
        if self.phase == "insert":
            goal = np.array([*(robot.eef_pos[:2] + to_peg), self.insert_z])
            action, _, _ = self._move(robot, goal, 1.0, SLOW)
            if nut.pos[2] < self.insert_z + 0.01:
                self._go("release")
            return action
        return self._release_and_retreat(robot, self.carry_z)


def make_expert(task: str) -> Expert:
    """A fresh scripted expert for ``task``; a ValueError names the valid tasks otherwise."""
    classes = {"lift": LiftExpert, "can": CanExpert, "square": SquareExpert}
    if not isinstance(task, str) or task not in classes:
        raise ValueError(f"unknown task {task!r}; valid tasks: {', '.join(TASKS)}")
    return classes[task]()
