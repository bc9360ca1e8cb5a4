"""What every robot-side piece speaks: EEF deltas, robot snapshots, object poses, and their
protobuf messages (``EefAction``, ``RobotState``, ``TaskState`` objects).

One control tick's action is an ``EefDelta`` in the robot base frame: translation ``dp`` (m),
rotation ``drot`` (axis-angle, rad, composing on the left: ``R_next = Rot(drot) @ R``) and a
gripper target closure in [0, 1] (0 open, 1 closed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.core import topics
from services.pb.common_pb2 import Header
from services.pb.control_pb2 import EefAction
from services.pb.sensors_pb2 import RobotState, TaskState


@dataclass(frozen=True)
class EefDelta:
    """One control tick's end-effector delta in the base frame (see proto EefAction)."""

    dp: np.ndarray  # (3,) metres
    drot: np.ndarray  # (3,) axis-angle, radians; R_next = Rot(drot) @ R
    gripper: float  # target closure in [0, 1]

    @classmethod
    def hold(cls, gripper: float) -> EefDelta:
        return cls(np.zeros(3), np.zeros(3), float(gripper))


def kept_gripper(closure: float) -> float:
    """The gripper target that keeps a gripper as it reads ``closure``: closed (1) above half closed
    (on an object, short of fully closed), open (0) otherwise. Sending the reading itself would be a
    target where a position-controlled gripper holds no grip; sending 0 would drop what it holds."""
    return 1.0 if closure > 0.5 else 0.0


@dataclass(frozen=True)
class RobotSnapshot:
    """The arm at one instant (what ``RobotState`` carries)."""

    eef_pos: np.ndarray  # (3,) base frame
    eef_quat_wxyz: np.ndarray  # (4,) base frame
    joint_pos: np.ndarray  # (n,) arm joints (rad); the fingers are summarised in `gripper`
    joint_vel: np.ndarray  # (n,) rad/s
    gripper: float  # closure in [0, 1], 0 open, 1 closed


@dataclass(frozen=True)
class ObjectPose:
    pos: np.ndarray  # (3,) world
    quat_wxyz: np.ndarray  # (4,)


# -- actions ----------------------------------------------------------------------------------


def action_from_msg(action: EefAction) -> EefDelta:
    """Validate and convert a wire action; raises ValueError for the wrong shape or NaN."""
    dp = np.asarray(action.dp, dtype=np.float64)
    drot = np.asarray(action.drot, dtype=np.float64)
    if dp.shape != (3,) or drot.shape != (3,):
        raise ValueError(f"action needs dp and drot of 3 values, got {dp.shape} and {drot.shape}")
    if not (np.all(np.isfinite(dp)) and np.all(np.isfinite(drot)) and np.isfinite(action.gripper)):
        raise ValueError("action has non-finite values")
    return EefDelta(dp, drot, float(np.clip(action.gripper, 0.0, 1.0)))


def action_msg(delta: EefDelta) -> EefAction:
    return EefAction(dp=[float(v) for v in delta.dp], drot=[float(v) for v in delta.drot], gripper=delta.gripper)


# -- robot state ------------------------------------------------------------------------------


def state_msg(snapshot: RobotSnapshot, tick: int, stamp_ns: int, seq: int, episode_id: str) -> RobotState:
    return RobotState(
        header=Header(stamp_ns=stamp_ns, seq=seq, frame_id=topics.WORLD_FRAME),
        tick=tick,
        eef_pos=[float(v) for v in snapshot.eef_pos],
        eef_quat_wxyz=[float(v) for v in snapshot.eef_quat_wxyz],
        joint_pos=[float(v) for v in snapshot.joint_pos],
        joint_vel=[float(v) for v in snapshot.joint_vel],
        gripper=float(snapshot.gripper),
        episode_id=episode_id,
    )


def snapshot_from_msg(state: RobotState) -> RobotSnapshot:
    return RobotSnapshot(
        eef_pos=np.asarray(state.eef_pos, dtype=np.float64),
        eef_quat_wxyz=np.asarray(state.eef_quat_wxyz, dtype=np.float64),
        joint_pos=np.asarray(state.joint_pos, dtype=np.float64),
        joint_vel=np.asarray(state.joint_vel, dtype=np.float64),
        gripper=float(state.gripper),
    )


# -- task state (sim only) --------------------------------------------------------------------


def objects_from_msg(task: TaskState) -> dict[str, ObjectPose]:
    return {
        o.name: ObjectPose(pos=np.asarray(o.pos, dtype=np.float64), quat_wxyz=np.asarray(o.quat_wxyz, dtype=np.float64))
        for o in task.objects
    }
