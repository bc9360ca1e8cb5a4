from services.pb import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class TrainCommand(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    TRAIN_COMMAND_UNSPECIFIED: _ClassVar[TrainCommand]
    TRAIN_COMMAND_TRAIN: _ClassVar[TrainCommand]
    TRAIN_COMMAND_CANCEL: _ClassVar[TrainCommand]
    TRAIN_COMMAND_STATUS: _ClassVar[TrainCommand]

class TrainState(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    TRAIN_STATE_UNSPECIFIED: _ClassVar[TrainState]
    TRAIN_STATE_QUEUED: _ClassVar[TrainState]
    TRAIN_STATE_RUNNING: _ClassVar[TrainState]
    TRAIN_STATE_DONE: _ClassVar[TrainState]
    TRAIN_STATE_FAILED: _ClassVar[TrainState]
    TRAIN_STATE_STOPPED: _ClassVar[TrainState]
TRAIN_COMMAND_UNSPECIFIED: TrainCommand
TRAIN_COMMAND_TRAIN: TrainCommand
TRAIN_COMMAND_CANCEL: TrainCommand
TRAIN_COMMAND_STATUS: TrainCommand
TRAIN_STATE_UNSPECIFIED: TrainState
TRAIN_STATE_QUEUED: TrainState
TRAIN_STATE_RUNNING: TrainState
TRAIN_STATE_DONE: TrainState
TRAIN_STATE_FAILED: TrainState
TRAIN_STATE_STOPPED: TrainState

class TrainRequest(_message.Message):
    __slots__ = ("command", "job_id", "data", "out", "preset", "steps", "overrides")
    COMMAND_FIELD_NUMBER: _ClassVar[int]
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    OUT_FIELD_NUMBER: _ClassVar[int]
    PRESET_FIELD_NUMBER: _ClassVar[int]
    STEPS_FIELD_NUMBER: _ClassVar[int]
    OVERRIDES_FIELD_NUMBER: _ClassVar[int]
    command: TrainCommand
    job_id: str
    data: str
    out: str
    preset: str
    steps: int
    overrides: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, command: _Optional[_Union[TrainCommand, str]] = ..., job_id: _Optional[str] = ..., data: _Optional[str] = ..., out: _Optional[str] = ..., preset: _Optional[str] = ..., steps: _Optional[int] = ..., overrides: _Optional[_Iterable[str]] = ...) -> None: ...

class TrainReply(_message.Message):
    __slots__ = ("ok", "error", "job_id", "running", "queued")
    OK_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    RUNNING_FIELD_NUMBER: _ClassVar[int]
    QUEUED_FIELD_NUMBER: _ClassVar[int]
    ok: bool
    error: str
    job_id: str
    running: str
    queued: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, ok: _Optional[bool] = ..., error: _Optional[str] = ..., job_id: _Optional[str] = ..., running: _Optional[str] = ..., queued: _Optional[_Iterable[str]] = ...) -> None: ...

class TrainProgress(_message.Message):
    __slots__ = ("header", "job_id", "state", "step", "steps", "loss", "val_loss", "lr", "it_s", "samples_s", "eta_s", "data_wait", "out", "checkpoint", "error")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    STEPS_FIELD_NUMBER: _ClassVar[int]
    LOSS_FIELD_NUMBER: _ClassVar[int]
    VAL_LOSS_FIELD_NUMBER: _ClassVar[int]
    LR_FIELD_NUMBER: _ClassVar[int]
    IT_S_FIELD_NUMBER: _ClassVar[int]
    SAMPLES_S_FIELD_NUMBER: _ClassVar[int]
    ETA_S_FIELD_NUMBER: _ClassVar[int]
    DATA_WAIT_FIELD_NUMBER: _ClassVar[int]
    OUT_FIELD_NUMBER: _ClassVar[int]
    CHECKPOINT_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    header: _common_pb2.Header
    job_id: str
    state: TrainState
    step: int
    steps: int
    loss: float
    val_loss: float
    lr: float
    it_s: float
    samples_s: float
    eta_s: float
    data_wait: float
    out: str
    checkpoint: str
    error: str
    def __init__(self, header: _Optional[_Union[_common_pb2.Header, _Mapping]] = ..., job_id: _Optional[str] = ..., state: _Optional[_Union[TrainState, str]] = ..., step: _Optional[int] = ..., steps: _Optional[int] = ..., loss: _Optional[float] = ..., val_loss: _Optional[float] = ..., lr: _Optional[float] = ..., it_s: _Optional[float] = ..., samples_s: _Optional[float] = ..., eta_s: _Optional[float] = ..., data_wait: _Optional[float] = ..., out: _Optional[str] = ..., checkpoint: _Optional[str] = ..., error: _Optional[str] = ...) -> None: ...
