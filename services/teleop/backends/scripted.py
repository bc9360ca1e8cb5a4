"""Scripted experts as a teleop source: they read the sim's privileged task state."""

from __future__ import annotations

import numpy as np

from services.pb.sensors_pb2 import RobotState, TaskState
from services.core.robot_types import EefDelta, objects_from_msg, snapshot_from_msg
from services.teleop.backends.base import TeleopSource
from sim.experts import make_expert


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
