from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class EpisodeCommand(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    EPISODE_COMMAND_UNSPECIFIED: _ClassVar[EpisodeCommand]
    EPISODE_COMMAND_START: _ClassVar[EpisodeCommand]
    EPISODE_COMMAND_STOP: _ClassVar[EpisodeCommand]
    EPISODE_COMMAND_DISCARD: _ClassVar[EpisodeCommand]
    EPISODE_COMMAND_STATUS: _ClassVar[EpisodeCommand]

class SimCommand(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SIM_COMMAND_UNSPECIFIED: _ClassVar[SimCommand]
    SIM_COMMAND_RESET: _ClassVar[SimCommand]
    SIM_COMMAND_RUN: _ClassVar[SimCommand]
    SIM_COMMAND_PAUSE: _ClassVar[SimCommand]
EPISODE_COMMAND_UNSPECIFIED: EpisodeCommand
EPISODE_COMMAND_START: EpisodeCommand
EPISODE_COMMAND_STOP: EpisodeCommand
EPISODE_COMMAND_DISCARD: EpisodeCommand
EPISODE_COMMAND_STATUS: EpisodeCommand
SIM_COMMAND_UNSPECIFIED: SimCommand
SIM_COMMAND_RESET: SimCommand
SIM_COMMAND_RUN: SimCommand
SIM_COMMAND_PAUSE: SimCommand

class EpisodeMeta(_message.Message):
    __slots__ = ("episode_id", "task", "seed", "rig", "success", "control_hz", "achieved_hz", "ticks", "frames", "drops", "malformed", "flags", "start_ns", "end_ns", "path", "gaps", "stale_ticks", "clipped_ticks", "lockstep", "rerendered_from", "malformed_reasons", "command_sources")
    class FramesEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: int
        def __init__(self, key: _Optional[str] = ..., value: _Optional[int] = ...) -> None: ...
    class DropsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: int
        def __init__(self, key: _Optional[str] = ..., value: _Optional[int] = ...) -> None: ...
    class MalformedEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: int
        def __init__(self, key: _Optional[str] = ..., value: _Optional[int] = ...) -> None: ...
    class GapsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: int
        def __init__(self, key: _Optional[str] = ..., value: _Optional[int] = ...) -> None: ...
    class MalformedReasonsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: int
        def __init__(self, key: _Optional[str] = ..., value: _Optional[int] = ...) -> None: ...
    EPISODE_ID_FIELD_NUMBER: _ClassVar[int]
    TASK_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    RIG_FIELD_NUMBER: _ClassVar[int]
    SUCCESS_FIELD_NUMBER: _ClassVar[int]
    CONTROL_HZ_FIELD_NUMBER: _ClassVar[int]
    ACHIEVED_HZ_FIELD_NUMBER: _ClassVar[int]
    TICKS_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    DROPS_FIELD_NUMBER: _ClassVar[int]
    MALFORMED_FIELD_NUMBER: _ClassVar[int]
    FLAGS_FIELD_NUMBER: _ClassVar[int]
    START_NS_FIELD_NUMBER: _ClassVar[int]
    END_NS_FIELD_NUMBER: _ClassVar[int]
    PATH_FIELD_NUMBER: _ClassVar[int]
    GAPS_FIELD_NUMBER: _ClassVar[int]
    STALE_TICKS_FIELD_NUMBER: _ClassVar[int]
    CLIPPED_TICKS_FIELD_NUMBER: _ClassVar[int]
    LOCKSTEP_FIELD_NUMBER: _ClassVar[int]
    RERENDERED_FROM_FIELD_NUMBER: _ClassVar[int]
    MALFORMED_REASONS_FIELD_NUMBER: _ClassVar[int]
    COMMAND_SOURCES_FIELD_NUMBER: _ClassVar[int]
    episode_id: str
    task: str
    seed: int
    rig: str
    success: bool
    control_hz: float
    achieved_hz: float
    ticks: int
    frames: _containers.ScalarMap[str, int]
    drops: _containers.ScalarMap[str, int]
    malformed: _containers.ScalarMap[str, int]
    flags: _containers.RepeatedScalarFieldContainer[str]
    start_ns: int
    end_ns: int
    path: str
    gaps: _containers.ScalarMap[str, int]
    stale_ticks: int
    clipped_ticks: int
    lockstep: bool
    rerendered_from: str
    malformed_reasons: _containers.ScalarMap[str, int]
    command_sources: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, episode_id: _Optional[str] = ..., task: _Optional[str] = ..., seed: _Optional[int] = ..., rig: _Optional[str] = ..., success: _Optional[bool] = ..., control_hz: _Optional[float] = ..., achieved_hz: _Optional[float] = ..., ticks: _Optional[int] = ..., frames: _Optional[_Mapping[str, int]] = ..., drops: _Optional[_Mapping[str, int]] = ..., malformed: _Optional[_Mapping[str, int]] = ..., flags: _Optional[_Iterable[str]] = ..., start_ns: _Optional[int] = ..., end_ns: _Optional[int] = ..., path: _Optional[str] = ..., gaps: _Optional[_Mapping[str, int]] = ..., stale_ticks: _Optional[int] = ..., clipped_ticks: _Optional[int] = ..., lockstep: _Optional[bool] = ..., rerendered_from: _Optional[str] = ..., malformed_reasons: _Optional[_Mapping[str, int]] = ..., command_sources: _Optional[_Iterable[str]] = ...) -> None: ...

class EpisodeRequest(_message.Message):
    __slots__ = ("command", "episode_id", "task", "seed", "rig", "control_hz", "success", "ticks", "lockstep", "interrupted")
    COMMAND_FIELD_NUMBER: _ClassVar[int]
    EPISODE_ID_FIELD_NUMBER: _ClassVar[int]
    TASK_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    RIG_FIELD_NUMBER: _ClassVar[int]
    CONTROL_HZ_FIELD_NUMBER: _ClassVar[int]
    SUCCESS_FIELD_NUMBER: _ClassVar[int]
    TICKS_FIELD_NUMBER: _ClassVar[int]
    LOCKSTEP_FIELD_NUMBER: _ClassVar[int]
    INTERRUPTED_FIELD_NUMBER: _ClassVar[int]
    command: EpisodeCommand
    episode_id: str
    task: str
    seed: int
    rig: str
    control_hz: float
    success: bool
    ticks: int
    lockstep: bool
    interrupted: str
    def __init__(self, command: _Optional[_Union[EpisodeCommand, str]] = ..., episode_id: _Optional[str] = ..., task: _Optional[str] = ..., seed: _Optional[int] = ..., rig: _Optional[str] = ..., control_hz: _Optional[float] = ..., success: _Optional[bool] = ..., ticks: _Optional[int] = ..., lockstep: _Optional[bool] = ..., interrupted: _Optional[str] = ...) -> None: ...

class EpisodeReply(_message.Message):
    __slots__ = ("ok", "error", "recording", "meta")
    OK_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    RECORDING_FIELD_NUMBER: _ClassVar[int]
    META_FIELD_NUMBER: _ClassVar[int]
    ok: bool
    error: str
    recording: bool
    meta: EpisodeMeta
    def __init__(self, ok: _Optional[bool] = ..., error: _Optional[str] = ..., recording: _Optional[bool] = ..., meta: _Optional[_Union[EpisodeMeta, _Mapping]] = ...) -> None: ...

class SimControlRequest(_message.Message):
    __slots__ = ("command", "task", "seed", "episode_id", "max_ticks", "settle_ticks")
    COMMAND_FIELD_NUMBER: _ClassVar[int]
    TASK_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    EPISODE_ID_FIELD_NUMBER: _ClassVar[int]
    MAX_TICKS_FIELD_NUMBER: _ClassVar[int]
    SETTLE_TICKS_FIELD_NUMBER: _ClassVar[int]
    command: SimCommand
    task: str
    seed: int
    episode_id: str
    max_ticks: int
    settle_ticks: int
    def __init__(self, command: _Optional[_Union[SimCommand, str]] = ..., task: _Optional[str] = ..., seed: _Optional[int] = ..., episode_id: _Optional[str] = ..., max_ticks: _Optional[int] = ..., settle_ticks: _Optional[int] = ...) -> None: ...

class SimControlReply(_message.Message):
    __slots__ = ("ok", "error", "ticks", "success", "lockstep")
    OK_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    TICKS_FIELD_NUMBER: _ClassVar[int]
    SUCCESS_FIELD_NUMBER: _ClassVar[int]
    LOCKSTEP_FIELD_NUMBER: _ClassVar[int]
    ok: bool
    error: str
    ticks: int
    success: bool
    lockstep: bool
    def __init__(self, ok: _Optional[bool] = ..., error: _Optional[str] = ..., ticks: _Optional[int] = ..., success: _Optional[bool] = ..., lockstep: _Optional[bool] = ...) -> None: ...
