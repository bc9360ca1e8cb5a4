from services.pb import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class RobotState(_message.Message):
    __slots__ = ("header", "tick", "eef_pos", "eef_quat_wxyz", "joint_pos", "joint_vel", "gripper", "episode_id")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    TICK_FIELD_NUMBER: _ClassVar[int]
    EEF_POS_FIELD_NUMBER: _ClassVar[int]
    EEF_QUAT_WXYZ_FIELD_NUMBER: _ClassVar[int]
    JOINT_POS_FIELD_NUMBER: _ClassVar[int]
    JOINT_VEL_FIELD_NUMBER: _ClassVar[int]
    GRIPPER_FIELD_NUMBER: _ClassVar[int]
    EPISODE_ID_FIELD_NUMBER: _ClassVar[int]
    header: _common_pb2.Header
    tick: int
    eef_pos: _containers.RepeatedScalarFieldContainer[float]
    eef_quat_wxyz: _containers.RepeatedScalarFieldContainer[float]
    joint_pos: _containers.RepeatedScalarFieldContainer[float]
    joint_vel: _containers.RepeatedScalarFieldContainer[float]
    gripper: float
    episode_id: str
    def __init__(self, header: _Optional[_Union[_common_pb2.Header, _Mapping]] = ..., tick: _Optional[int] = ..., eef_pos: _Optional[_Iterable[float]] = ..., eef_quat_wxyz: _Optional[_Iterable[float]] = ..., joint_pos: _Optional[_Iterable[float]] = ..., joint_vel: _Optional[_Iterable[float]] = ..., gripper: _Optional[float] = ..., episode_id: _Optional[str] = ...) -> None: ...

class ObjectPose(_message.Message):
    __slots__ = ("name", "pos", "quat_wxyz")
    NAME_FIELD_NUMBER: _ClassVar[int]
    POS_FIELD_NUMBER: _ClassVar[int]
    QUAT_WXYZ_FIELD_NUMBER: _ClassVar[int]
    name: str
    pos: _containers.RepeatedScalarFieldContainer[float]
    quat_wxyz: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, name: _Optional[str] = ..., pos: _Optional[_Iterable[float]] = ..., quat_wxyz: _Optional[_Iterable[float]] = ...) -> None: ...

class TaskState(_message.Message):
    __slots__ = ("header", "tick", "task", "seed", "episode_id", "objects", "success")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    TICK_FIELD_NUMBER: _ClassVar[int]
    TASK_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    EPISODE_ID_FIELD_NUMBER: _ClassVar[int]
    OBJECTS_FIELD_NUMBER: _ClassVar[int]
    SUCCESS_FIELD_NUMBER: _ClassVar[int]
    header: _common_pb2.Header
    tick: int
    task: str
    seed: int
    episode_id: str
    objects: _containers.RepeatedCompositeFieldContainer[ObjectPose]
    success: bool
    def __init__(self, header: _Optional[_Union[_common_pb2.Header, _Mapping]] = ..., tick: _Optional[int] = ..., task: _Optional[str] = ..., seed: _Optional[int] = ..., episode_id: _Optional[str] = ..., objects: _Optional[_Iterable[_Union[ObjectPose, _Mapping]]] = ..., success: _Optional[bool] = ...) -> None: ...
