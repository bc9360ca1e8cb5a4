from services.pb import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class EefAction(_message.Message):
    __slots__ = ("dp", "drot", "gripper")
    DP_FIELD_NUMBER: _ClassVar[int]
    DROT_FIELD_NUMBER: _ClassVar[int]
    GRIPPER_FIELD_NUMBER: _ClassVar[int]
    dp: _containers.RepeatedScalarFieldContainer[float]
    drot: _containers.RepeatedScalarFieldContainer[float]
    gripper: float
    def __init__(self, dp: _Optional[_Iterable[float]] = ..., drot: _Optional[_Iterable[float]] = ..., gripper: _Optional[float] = ...) -> None: ...

class EefCommand(_message.Message):
    __slots__ = ("header", "tick", "action", "source")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    TICK_FIELD_NUMBER: _ClassVar[int]
    ACTION_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    header: _common_pb2.Header
    tick: int
    action: EefAction
    source: str
    def __init__(self, header: _Optional[_Union[_common_pb2.Header, _Mapping]] = ..., tick: _Optional[int] = ..., action: _Optional[_Union[EefAction, _Mapping]] = ..., source: _Optional[str] = ...) -> None: ...

class AppliedAction(_message.Message):
    __slots__ = ("header", "tick", "action", "stale", "limits", "fault")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    TICK_FIELD_NUMBER: _ClassVar[int]
    ACTION_FIELD_NUMBER: _ClassVar[int]
    STALE_FIELD_NUMBER: _ClassVar[int]
    LIMITS_FIELD_NUMBER: _ClassVar[int]
    FAULT_FIELD_NUMBER: _ClassVar[int]
    header: _common_pb2.Header
    tick: int
    action: EefAction
    stale: bool
    limits: _containers.RepeatedScalarFieldContainer[str]
    fault: str
    def __init__(self, header: _Optional[_Union[_common_pb2.Header, _Mapping]] = ..., tick: _Optional[int] = ..., action: _Optional[_Union[EefAction, _Mapping]] = ..., stale: _Optional[bool] = ..., limits: _Optional[_Iterable[str]] = ..., fault: _Optional[str] = ...) -> None: ...
