"""Every Zenoh key expression with its message type: the session's graph, declared once.

Keys are relative to the bus namespace (``BusConfig.namespace``, default ``vs``). The recorder
writes each topic to an MCAP channel named ``/`` + key, so the same names appear in Foxglove.
Camera topics are per camera name; use the ``camera_*`` helpers to build them.
"""

from __future__ import annotations

from dataclasses import dataclass

from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from google.protobuf.message import Message

from services.pb import control_pb2, episode_pb2, sensors_pb2, trainer_pb2


@dataclass(frozen=True)
class Topic:
    key: str  # relative key expression
    msg_type: type[Message]

    @property
    def mcap_topic(self) -> str:
        return "/" + self.key


def camera_image(name: str) -> Topic:
    """JPEG frames of one camera (capture time in ``timestamp``, frame_id = camera name)."""
    return Topic(f"camera/{name}/image", CompressedImage)


def camera_calibration(name: str) -> Topic:
    """Intrinsics (OpenCV pinhole, no distortion in sim) of one camera, republished at 1 Hz."""
    return Topic(f"camera/{name}/calibration", CameraCalibration)


def camera_pose(name: str) -> Topic:
    """Pose of the camera's optical frame (x right, y down, z forward) in the ``world`` frame."""
    return Topic(f"camera/{name}/pose", FrameTransform)


ROBOT_STATE = Topic("robot/state", sensors_pb2.RobotState)
APPLIED_ACTION = Topic("robot/applied", control_pb2.AppliedAction)
COMMAND = Topic("teleop/command", control_pb2.EefCommand)
TASK_STATE = Topic("sim/task", sensors_pb2.TaskState)
EPISODE = Topic("recorder/episode", episode_pb2.EpisodeMeta)  # the recorder's episodes: started (end_ns 0), closed
TRAIN_PROGRESS = Topic("trainer/progress", trainer_pb2.TrainProgress)  # the trainer service's runs

# Queryables (request/reply, protobuf both ways).
EPISODE_CONTROL = "recorder/control"  # EpisodeRequest -> EpisodeReply
SIM_CONTROL = "sim/control"  # SimControlRequest -> SimControlReply
TRAIN_REQUEST = "trainer/request"  # TrainRequest -> TrainReply

WORLD_FRAME = "world"


def session_topics(cameras: list[str]) -> list[Topic]:
    """Everything a collection session publishes for a rig with ``cameras``."""
    topics = [ROBOT_STATE, APPLIED_ACTION, COMMAND, TASK_STATE]
    for name in cameras:
        topics += [camera_image(name), camera_calibration(name), camera_pose(name)]
    return topics


def topic_for_key(key: str) -> Topic | None:
    """Map a received key of a collection session back to its Topic (None for anything else,
    trainer progress included: the recorder records exactly what this maps)."""
    fixed = {t.key: t for t in (ROBOT_STATE, APPLIED_ACTION, COMMAND, TASK_STATE, EPISODE)}
    if key in fixed:
        return fixed[key]
    parts = key.split("/")
    if len(parts) == 3 and parts[0] == "camera":
        make = {"image": camera_image, "calibration": camera_calibration, "pose": camera_pose}.get(parts[2])
        if make is not None:
            return make(parts[1])
    return None
