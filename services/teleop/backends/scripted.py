"""Scripted experts as a teleop source: they read the sim's privileged task state."""

from __future__ import annotations

import numpy as np

from services.pb.sensors_pb2 import RobotState, TaskState
from services.robot.backends.base import EefDelta
from services.teleop.backends.base import TeleopSource
from sim.experts import make_expert
from sim.world import ObjectPose, RobotSnapshot


def snapshot_from_msg(state: RobotState) -> RobotSnapshot:
    return RobotSnapshot(
        eef_pos=np.asarray(state.eef_pos, dtype=np.float64),
        eef_quat_wxyz=np.asarray(state.eef_quat_wxyz, dtype=np.float64),
        joint_pos=np.asarray(state.joint_pos, dtype=np.float64),
        joint_vel=np.asarray(state.joint_vel, dtype=np.float64),
        gripper=float(state.gripper),
    )


def objects_from_msg(task: TaskState) -> dict[str, ObjectPose]:
    return {
        o.name: ObjectPose(pos=np.asarray(o.pos, dtype=np.float64), quat_wxyz=np.asarray(o.quat_wxyz, dtype=np.float64))
        for o in task.objects
    }


class ScriptedSource(TeleopSource):
    needs_task_state = True

    def __init__(self):
        self._expert = None
        self._task = ""

    def reset(self, task: str) -> None:
        if task != self._task or self._expert is None:
            self._expert = make_expert(task)
            self._task = task
        self._expert.reset()

    def act(self, state: RobotState, task: TaskState | None) -> EefDelta:
        if task is None:
            raise ValueError("the scripted expert needs the task state of the same tick")
        if self._expert is None or task.task != self._task:
            self.reset(task.task)
        dp, drot, gripper = self._expert.act(snapshot_from_msg(state), objects_from_msg(task))
        return EefDelta(np.asarray(dp, dtype=np.float64), np.asarray(drot, dtype=np.float64), float(gripper))
