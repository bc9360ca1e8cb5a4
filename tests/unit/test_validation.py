"""Well-formed but wrong messages are refused with a reason (services/core/validation.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.core.rig import load_rig
from services.core.tensors import compressed_image
from services.core.topics import (
    APPLIED_ACTION,
    COMMAND,
    ROBOT_STATE,
    TASK_STATE,
    camera_calibration,
    camera_image,
    camera_pose,
)
from services.core.validation import Context, Invalid, check_episode_request, check_sim_request, parse
from services.pb.common_pb2 import Header
from services.pb.control_pb2 import AppliedAction, EefAction, EefCommand
from services.pb.episode_pb2 import EpisodeCommand, EpisodeRequest, SimCommand, SimControlRequest
from services.pb.sensors_pb2 import ObjectPose, RobotState, TaskState

T0 = 1_700_000_000_000_000_000
CAM = load_rig("five15").cameras["F"]


def state(**kw) -> RobotState:
    base = dict(
        header=Header(stamp_ns=T0, seq=1),
        tick=1,
        eef_pos=[0.4, 0.0, 0.2],
        eef_quat_wxyz=[0, 1, 0, 0],
        joint_pos=[0.0] * 6,
        joint_vel=[0.0] * 6,
        gripper=0.0,
        episode_id="ep",
    )
    base.update(kw)
    return RobotState(**base)


def action(**kw) -> EefAction:
    base = dict(dp=[0.01, 0, 0], drot=[0, 0, 0.1], gripper=1.0)
    base.update(kw)
    return EefAction(**base)


def image(w: int, h: int, frame_id: str = "F"):
    return compressed_image(np.zeros((h, w, 3), np.uint8), T0, frame_id)


def calibration(**kw):
    msg = CAM.calibration_msg(84, 84, T0)
    for k, v in kw.items():
        if isinstance(v, list):
            del getattr(msg, k)[:]
            getattr(msg, k).extend(v)
        else:
            setattr(msg, k, v)
    return msg


CTX = Context(episode_id="ep", image_sizes={"F": (84, 84)})
NAN, INF = math.nan, math.inf

GOOD = [
    (ROBOT_STATE, state()),
    (APPLIED_ACTION, AppliedAction(header=Header(stamp_ns=T0), tick=1, action=action(), limits=["speed"])),
    (COMMAND, EefCommand(header=Header(stamp_ns=T0), tick=1, action=action(), source="scripted")),
    (
        TASK_STATE,
        TaskState(
            header=Header(stamp_ns=T0),
            task="lift",
            episode_id="ep",
            objects=[ObjectPose(name="cube", pos=[0.5, 0, 0.02], quat_wxyz=[1, 0, 0, 0])],
        ),
    ),
    (camera_image("F"), image(84, 84)),
    (camera_calibration("F"), calibration()),
    (camera_pose("F"), CAM.pose_msg(T0)),
]

BAD = {
    "NaN position": (ROBOT_STATE, state(eef_pos=[0.4, NAN, 0.2]), "non-finite"),
    "infinite joint velocity": (ROBOT_STATE, state(joint_vel=[0, 0, INF, 0, 0, 0]), "non-finite"),
    "a pose 50 m away": (ROBOT_STATE, state(eef_pos=[50.0, 0, 0]), "out of range"),
    "non-unit quaternion": (ROBOT_STATE, state(eef_quat_wxyz=[0, 2, 0, 0]), "not a unit quaternion"),
    "gripper 7": (ROBOT_STATE, state(gripper=7.0), "out of range"),
    "another episode's state": (ROBOT_STATE, state(episode_id="other"), "another episode"),
    "a 5 MB episode id": (ROBOT_STATE, state(episode_id="x" * (5 << 20)), "oversized field"),
    "NaN command": (
        COMMAND,
        EefCommand(header=Header(stamp_ns=T0), tick=1, action=action(dp=[NAN, 0, 0])),
        "non-finite",
    ),
    "a 3 m step": (
        APPLIED_ACTION,
        AppliedAction(header=Header(stamp_ns=T0), action=action(dp=[3.0, 0, 0])),
        "out of range",
    ),
    "a short rotation": (COMMAND, EefCommand(header=Header(stamp_ns=T0), action=action(drot=[0.1])), "wrong length"),
    "an unknown limit": (
        APPLIED_ACTION,
        AppliedAction(header=Header(stamp_ns=T0), action=action(), limits=["warp"]),
        "out of range",
    ),
    "object with NaN": (
        TASK_STATE,
        TaskState(
            header=Header(stamp_ns=T0),
            task="lift",
            episode_id="ep",
            objects=[ObjectPose(name="cube", pos=[NAN, 0, 0], quat_wxyz=[1, 0, 0, 0])],
        ),
        "non-finite",
    ),
    "another episode's task": (
        TASK_STATE,
        TaskState(header=Header(stamp_ns=T0), task="lift", episode_id="zz"),
        "another episode",
    ),
    "frame of the wrong size": (camera_image("F"), image(64, 48), "wrong image size"),
    "calibration with NaN K": (camera_calibration("F"), calibration(K=[NAN] + [0.0] * 8), "non-finite"),
    "calibration of size 0": (camera_calibration("F"), calibration(width=0), "bad calibration"),
    "calibration too large": (camera_calibration("F"), calibration(width=1 << 20), "bad calibration"),
    "calibration with infinite distortion": (camera_calibration("F"), calibration(D=[INF, 0, 0, 0, 0]), "non-finite"),
}


@pytest.mark.parametrize("topic, msg", GOOD, ids=[t.key for t, _ in GOOD])
def test_good_messages_pass(topic, msg):
    assert parse(topic, msg.SerializeToString(), ctx=CTX) == msg


@pytest.mark.parametrize("case", list(BAD))
def test_wrong_values_are_refused_with_their_reason(case):
    topic, msg, reason = BAD[case]
    with pytest.raises(Invalid) as err:
        parse(topic, msg.SerializeToString(), ctx=CTX)
    assert err.value.reason == reason, str(err.value)


def test_a_pose_with_a_non_unit_rotation_is_refused():
    pose = CAM.pose_msg(T0)
    pose.rotation.w += 0.5
    with pytest.raises(Invalid, match="not a unit quaternion"):
        parse(camera_pose("F"), pose.SerializeToString(), ctx=CTX)


def test_control_requests_of_another_type_or_with_absurd_values_are_refused():
    check_episode_request(EpisodeRequest(command=EpisodeCommand.EPISODE_COMMAND_STOP, ticks=100), max_ticks=1000)
    with pytest.raises(Invalid, match="ticks = 1000000000"):
        check_episode_request(EpisodeRequest(command=EpisodeCommand.EPISODE_COMMAND_STOP, ticks=10**9), max_ticks=1000)
    with pytest.raises(Invalid, match="unknown episode command"):
        check_episode_request(EpisodeRequest(command=0), max_ticks=1000)
    with pytest.raises(Invalid, match="control_hz"):
        check_episode_request(EpisodeRequest(command=EpisodeCommand.EPISODE_COMMAND_START, control_hz=NAN), 1000)
    with pytest.raises(Invalid, match="unknown task"):
        check_sim_request(SimControlRequest(command=SimCommand.SIM_COMMAND_RESET, task="pour"), ("lift", "can"))


def test_our_own_text_fields_may_be_long_but_ids_may_not():
    from services.core.validation import check
    from services.pb.episode_pb2 import EpisodeMeta

    long_flag = "malformed payloads (" + ", ".join(f"/camera/C{i}/image: 300" for i in range(12)) + ")"
    assert 256 < len(long_flag) < 4096
    check(EpisodeMeta(episode_id="lift-five15-0001", flags=[long_flag]))
    with pytest.raises(Invalid, match="flags"):
        check(EpisodeMeta(episode_id="lift-five15-0001", flags=["x" * 5000]))
    with pytest.raises(Invalid, match="episode_id holds 300"):
        check(EpisodeMeta(episode_id="x" * 300, flags=[long_flag]))
