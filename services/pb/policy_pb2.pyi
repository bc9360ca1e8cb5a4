from services.pb import common_pb2 as _common_pb2
from services.pb import control_pb2 as _control_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class PolicyInfoRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class CameraInfo(_message.Message):
    __slots__ = ("name", "width", "height", "K", "R_ext", "position", "default_gamma")
    NAME_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    R_EXT_FIELD_NUMBER: _ClassVar[int]
    POSITION_FIELD_NUMBER: _ClassVar[int]
    DEFAULT_GAMMA_FIELD_NUMBER: _ClassVar[int]
    name: str
    width: int
    height: int
    K: _containers.RepeatedScalarFieldContainer[float]
    R_ext: _containers.RepeatedScalarFieldContainer[float]
    position: _containers.RepeatedScalarFieldContainer[float]
    default_gamma: float
    def __init__(self, name: _Optional[str] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., K: _Optional[_Iterable[float]] = ..., R_ext: _Optional[_Iterable[float]] = ..., position: _Optional[_Iterable[float]] = ..., default_gamma: _Optional[float] = ...) -> None: ...

class PolicyInfo(_message.Message):
    __slots__ = ("proto_version", "model_id", "checkpoint_sha256", "action_space", "state_frame", "obs_horizon", "pred_horizon", "n_action_steps", "control_hz", "image_width", "image_height", "ddim_steps", "cameras", "unconditional", "default_views", "server_instance", "precision")
    PROTO_VERSION_FIELD_NUMBER: _ClassVar[int]
    MODEL_ID_FIELD_NUMBER: _ClassVar[int]
    CHECKPOINT_SHA256_FIELD_NUMBER: _ClassVar[int]
    ACTION_SPACE_FIELD_NUMBER: _ClassVar[int]
    STATE_FRAME_FIELD_NUMBER: _ClassVar[int]
    OBS_HORIZON_FIELD_NUMBER: _ClassVar[int]
    PRED_HORIZON_FIELD_NUMBER: _ClassVar[int]
    N_ACTION_STEPS_FIELD_NUMBER: _ClassVar[int]
    CONTROL_HZ_FIELD_NUMBER: _ClassVar[int]
    IMAGE_WIDTH_FIELD_NUMBER: _ClassVar[int]
    IMAGE_HEIGHT_FIELD_NUMBER: _ClassVar[int]
    DDIM_STEPS_FIELD_NUMBER: _ClassVar[int]
    CAMERAS_FIELD_NUMBER: _ClassVar[int]
    UNCONDITIONAL_FIELD_NUMBER: _ClassVar[int]
    DEFAULT_VIEWS_FIELD_NUMBER: _ClassVar[int]
    SERVER_INSTANCE_FIELD_NUMBER: _ClassVar[int]
    PRECISION_FIELD_NUMBER: _ClassVar[int]
    proto_version: int
    model_id: str
    checkpoint_sha256: str
    action_space: str
    state_frame: str
    obs_horizon: int
    pred_horizon: int
    n_action_steps: int
    control_hz: float
    image_width: int
    image_height: int
    ddim_steps: int
    cameras: _containers.RepeatedCompositeFieldContainer[CameraInfo]
    unconditional: bool
    default_views: _containers.RepeatedScalarFieldContainer[str]
    server_instance: str
    precision: str
    def __init__(self, proto_version: _Optional[int] = ..., model_id: _Optional[str] = ..., checkpoint_sha256: _Optional[str] = ..., action_space: _Optional[str] = ..., state_frame: _Optional[str] = ..., obs_horizon: _Optional[int] = ..., pred_horizon: _Optional[int] = ..., n_action_steps: _Optional[int] = ..., control_hz: _Optional[float] = ..., image_width: _Optional[int] = ..., image_height: _Optional[int] = ..., ddim_steps: _Optional[int] = ..., cameras: _Optional[_Iterable[_Union[CameraInfo, _Mapping]]] = ..., unconditional: _Optional[bool] = ..., default_views: _Optional[_Iterable[str]] = ..., server_instance: _Optional[str] = ..., precision: _Optional[str] = ...) -> None: ...

class Frame(_message.Message):
    __slots__ = ("jpeg", "rgb", "stamp_ns")
    JPEG_FIELD_NUMBER: _ClassVar[int]
    RGB_FIELD_NUMBER: _ClassVar[int]
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    jpeg: bytes
    rgb: _common_pb2.Tensor
    stamp_ns: int
    def __init__(self, jpeg: _Optional[bytes] = ..., rgb: _Optional[_Union[_common_pb2.Tensor, _Mapping]] = ..., stamp_ns: _Optional[int] = ...) -> None: ...

class CameraFrames(_message.Message):
    __slots__ = ("name", "frames")
    NAME_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    name: str
    frames: _containers.RepeatedCompositeFieldContainer[Frame]
    def __init__(self, name: _Optional[str] = ..., frames: _Optional[_Iterable[_Union[Frame, _Mapping]]] = ...) -> None: ...

class StateSample(_message.Message):
    __slots__ = ("stamp_ns", "eef_pos", "eef_quat_wxyz", "gripper")
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    EEF_POS_FIELD_NUMBER: _ClassVar[int]
    EEF_QUAT_WXYZ_FIELD_NUMBER: _ClassVar[int]
    GRIPPER_FIELD_NUMBER: _ClassVar[int]
    stamp_ns: int
    eef_pos: _containers.RepeatedScalarFieldContainer[float]
    eef_quat_wxyz: _containers.RepeatedScalarFieldContainer[float]
    gripper: float
    def __init__(self, stamp_ns: _Optional[int] = ..., eef_pos: _Optional[_Iterable[float]] = ..., eef_quat_wxyz: _Optional[_Iterable[float]] = ..., gripper: _Optional[float] = ...) -> None: ...

class ActionRequest(_message.Message):
    __slots__ = ("session_id", "seq", "cameras", "states", "views", "gamma", "seed", "unconditional")
    class GammaEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    CAMERAS_FIELD_NUMBER: _ClassVar[int]
    STATES_FIELD_NUMBER: _ClassVar[int]
    VIEWS_FIELD_NUMBER: _ClassVar[int]
    GAMMA_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    UNCONDITIONAL_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    seq: int
    cameras: _containers.RepeatedCompositeFieldContainer[CameraFrames]
    states: _containers.RepeatedCompositeFieldContainer[StateSample]
    views: _containers.RepeatedScalarFieldContainer[str]
    gamma: _containers.ScalarMap[str, float]
    seed: int
    unconditional: bool
    def __init__(self, session_id: _Optional[str] = ..., seq: _Optional[int] = ..., cameras: _Optional[_Iterable[_Union[CameraFrames, _Mapping]]] = ..., states: _Optional[_Iterable[_Union[StateSample, _Mapping]]] = ..., views: _Optional[_Iterable[str]] = ..., gamma: _Optional[_Mapping[str, float]] = ..., seed: _Optional[int] = ..., unconditional: _Optional[bool] = ...) -> None: ...

class Timing(_message.Message):
    __slots__ = ("decode_ms", "encode_ms", "step_p50_ms", "step_max_ms", "total_ms", "server_receive_ns", "server_send_ns")
    DECODE_MS_FIELD_NUMBER: _ClassVar[int]
    ENCODE_MS_FIELD_NUMBER: _ClassVar[int]
    STEP_P50_MS_FIELD_NUMBER: _ClassVar[int]
    STEP_MAX_MS_FIELD_NUMBER: _ClassVar[int]
    TOTAL_MS_FIELD_NUMBER: _ClassVar[int]
    SERVER_RECEIVE_NS_FIELD_NUMBER: _ClassVar[int]
    SERVER_SEND_NS_FIELD_NUMBER: _ClassVar[int]
    decode_ms: float
    encode_ms: float
    step_p50_ms: float
    step_max_ms: float
    total_ms: float
    server_receive_ns: int
    server_send_ns: int
    def __init__(self, decode_ms: _Optional[float] = ..., encode_ms: _Optional[float] = ..., step_p50_ms: _Optional[float] = ..., step_max_ms: _Optional[float] = ..., total_ms: _Optional[float] = ..., server_receive_ns: _Optional[int] = ..., server_send_ns: _Optional[int] = ...) -> None: ...

class ActionReply(_message.Message):
    __slots__ = ("seq", "actions", "start_index", "obs_stamp_ns", "views_used", "degraded", "degraded_reasons", "timing", "checkpoint_sha256", "server_instance")
    SEQ_FIELD_NUMBER: _ClassVar[int]
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    START_INDEX_FIELD_NUMBER: _ClassVar[int]
    OBS_STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    VIEWS_USED_FIELD_NUMBER: _ClassVar[int]
    DEGRADED_FIELD_NUMBER: _ClassVar[int]
    DEGRADED_REASONS_FIELD_NUMBER: _ClassVar[int]
    TIMING_FIELD_NUMBER: _ClassVar[int]
    CHECKPOINT_SHA256_FIELD_NUMBER: _ClassVar[int]
    SERVER_INSTANCE_FIELD_NUMBER: _ClassVar[int]
    seq: int
    actions: _containers.RepeatedCompositeFieldContainer[_control_pb2.EefAction]
    start_index: int
    obs_stamp_ns: int
    views_used: _containers.RepeatedScalarFieldContainer[str]
    degraded: bool
    degraded_reasons: _containers.RepeatedScalarFieldContainer[str]
    timing: Timing
    checkpoint_sha256: str
    server_instance: str
    def __init__(self, seq: _Optional[int] = ..., actions: _Optional[_Iterable[_Union[_control_pb2.EefAction, _Mapping]]] = ..., start_index: _Optional[int] = ..., obs_stamp_ns: _Optional[int] = ..., views_used: _Optional[_Iterable[str]] = ..., degraded: _Optional[bool] = ..., degraded_reasons: _Optional[_Iterable[str]] = ..., timing: _Optional[_Union[Timing, _Mapping]] = ..., checkpoint_sha256: _Optional[str] = ..., server_instance: _Optional[str] = ...) -> None: ...

class ResetRequest(_message.Message):
    __slots__ = ("session_id", "seed")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    seed: int
    def __init__(self, session_id: _Optional[str] = ..., seed: _Optional[int] = ...) -> None: ...

class ResetReply(_message.Message):
    __slots__ = ("existed",)
    EXISTED_FIELD_NUMBER: _ClassVar[int]
    existed: bool
    def __init__(self, existed: _Optional[bool] = ...) -> None: ...

class DenoiseObservation(_message.Message):
    __slots__ = ("checkpoint_sha256", "view", "frames", "state", "unconditional", "group", "group_size", "precision")
    CHECKPOINT_SHA256_FIELD_NUMBER: _ClassVar[int]
    VIEW_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    UNCONDITIONAL_FIELD_NUMBER: _ClassVar[int]
    GROUP_FIELD_NUMBER: _ClassVar[int]
    GROUP_SIZE_FIELD_NUMBER: _ClassVar[int]
    PRECISION_FIELD_NUMBER: _ClassVar[int]
    checkpoint_sha256: str
    view: str
    frames: _common_pb2.Tensor
    state: _common_pb2.Tensor
    unconditional: bool
    group: str
    group_size: int
    precision: str
    def __init__(self, checkpoint_sha256: _Optional[str] = ..., view: _Optional[str] = ..., frames: _Optional[_Union[_common_pb2.Tensor, _Mapping]] = ..., state: _Optional[_Union[_common_pb2.Tensor, _Mapping]] = ..., unconditional: _Optional[bool] = ..., group: _Optional[str] = ..., group_size: _Optional[int] = ..., precision: _Optional[str] = ...) -> None: ...

class DenoiseStep(_message.Message):
    __slots__ = ("k", "x")
    K_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    k: int
    x: _common_pb2.Tensor
    def __init__(self, k: _Optional[int] = ..., x: _Optional[_Union[_common_pb2.Tensor, _Mapping]] = ...) -> None: ...

class DenoiseRequest(_message.Message):
    __slots__ = ("observation", "step")
    OBSERVATION_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    observation: DenoiseObservation
    step: DenoiseStep
    def __init__(self, observation: _Optional[_Union[DenoiseObservation, _Mapping]] = ..., step: _Optional[_Union[DenoiseStep, _Mapping]] = ...) -> None: ...

class DenoiseReply(_message.Message):
    __slots__ = ("eps", "eps_uncond", "compute_ms")
    EPS_FIELD_NUMBER: _ClassVar[int]
    EPS_UNCOND_FIELD_NUMBER: _ClassVar[int]
    COMPUTE_MS_FIELD_NUMBER: _ClassVar[int]
    eps: _common_pb2.Tensor
    eps_uncond: _common_pb2.Tensor
    compute_ms: float
    def __init__(self, eps: _Optional[_Union[_common_pb2.Tensor, _Mapping]] = ..., eps_uncond: _Optional[_Union[_common_pb2.Tensor, _Mapping]] = ..., compute_ms: _Optional[float] = ...) -> None: ...

class WorkerInfoRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class WorkerInfo(_message.Message):
    __slots__ = ("checkpoint_sha256", "model_id", "device", "threads", "max_batch", "streams", "passes", "batched_items", "max_streams", "machine", "cores", "accelerator", "precision")
    CHECKPOINT_SHA256_FIELD_NUMBER: _ClassVar[int]
    MODEL_ID_FIELD_NUMBER: _ClassVar[int]
    DEVICE_FIELD_NUMBER: _ClassVar[int]
    THREADS_FIELD_NUMBER: _ClassVar[int]
    MAX_BATCH_FIELD_NUMBER: _ClassVar[int]
    STREAMS_FIELD_NUMBER: _ClassVar[int]
    PASSES_FIELD_NUMBER: _ClassVar[int]
    BATCHED_ITEMS_FIELD_NUMBER: _ClassVar[int]
    MAX_STREAMS_FIELD_NUMBER: _ClassVar[int]
    MACHINE_FIELD_NUMBER: _ClassVar[int]
    CORES_FIELD_NUMBER: _ClassVar[int]
    ACCELERATOR_FIELD_NUMBER: _ClassVar[int]
    PRECISION_FIELD_NUMBER: _ClassVar[int]
    checkpoint_sha256: str
    model_id: str
    device: str
    threads: int
    max_batch: int
    streams: int
    passes: int
    batched_items: int
    max_streams: int
    machine: str
    cores: _containers.RepeatedScalarFieldContainer[int]
    accelerator: str
    precision: str
    def __init__(self, checkpoint_sha256: _Optional[str] = ..., model_id: _Optional[str] = ..., device: _Optional[str] = ..., threads: _Optional[int] = ..., max_batch: _Optional[int] = ..., streams: _Optional[int] = ..., passes: _Optional[int] = ..., batched_items: _Optional[int] = ..., max_streams: _Optional[int] = ..., machine: _Optional[str] = ..., cores: _Optional[_Iterable[int]] = ..., accelerator: _Optional[str] = ..., precision: _Optional[str] = ...) -> None: ...
