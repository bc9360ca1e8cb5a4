"""What makes a message of the session good, per message type, in one place.

A lab's bus is a shared network: anything that can publish there can reach the recorder, the
teleop and the robot. A payload is good when

1. it parses as its topic's message type with no field the schema does not know (bytes of another
   message type nearly always leave unknown fields behind: every publisher builds from this
   repository's schemas, so an unknown field means the wrong schema, not a newer one);
2. it carries a capture time;
3. its values make sense for its type (``check``): finite numbers, unit quaternions, actions and
   poses within physical bounds, image sizes and JPEGs that match their camera's calibration,
   bounded strings and counts, and -- in context -- the episode being recorded.

``parse`` does all three and raises ``Invalid`` with a short ``reason`` (what the counters are
keyed by) and a message (what the logs say). The recorder refuses what fails and counts it per
topic and reason; the control loop and the teleop apply the same checks to what they act on.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from google.protobuf.descriptor import FieldDescriptor
from google.protobuf.message import DecodeError, Message
from google.protobuf.unknown_fields import UnknownFieldSet

from services.core.tensors import ImageDecodeError, decode_jpeg, jpeg_size
from services.core.topics import Topic
from services.pb.common_pb2 import Header
from services.pb.control_pb2 import AppliedAction, EefAction, EefCommand
from services.pb.episode_pb2 import EpisodeCommand, EpisodeRequest, SimCommand, SimControlRequest
from services.pb.sensors_pb2 import RobotState, TaskState

MAX_STRING = 256  # any string field of a session message (ids, names, frame ids)
MAX_TEXT = 4096  # our own human-readable text: an episode's flags, a reply's error, a path
TEXT_FIELDS = {"flags", "error", "path", "rerendered_from"}
MAX_REPEATED = 64  # joints, objects, limits ...
MAX_POSITION_M = 10.0  # a pose farther than this from the base is not of this robot's workspace
MAX_STEP_M = 1.0  # one tick's translation
MAX_STEP_RAD = math.pi  # one tick's rotation
MAX_IMAGE_SIDE = 16384
UNIT_TOLERANCE = 1e-3  # |q| - 1 for quaternions
LIMITS = {"speed", "rotation", "workspace", "gripper"}  # AppliedAction.limits


class Invalid(ValueError):
    """A payload that is not written or acted on; ``reason`` is a short class, the message says more."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


@dataclass
class Context:
    """What a message is checked against beyond itself (the recorder's view of the session)."""

    episode_id: str = ""  # messages naming another episode are refused ('' = any)
    image_sizes: dict[str, tuple[int, int]] = field(default_factory=dict)  # camera -> (width, height) calibrated


# -- building blocks ----------------------------------------------------------------------------


def _unknown_field_path(msg: Message, path: str = "") -> str | None:
    """Dotted path of the first message holding fields its schema does not define."""
    if len(UnknownFieldSet(msg)):
        return path or msg.DESCRIPTOR.name
    for f, value in msg.ListFields():
        if f.type != FieldDescriptor.TYPE_MESSAGE:
            continue
        if f.message_type.GetOptions().map_entry:
            items = value.values() if f.message_type.fields_by_name["value"].message_type else []
        elif f.is_repeated:
            items = value
        else:
            items = [value]
        for item in items:
            found = _unknown_field_path(item, f"{path}.{f.name}" if path else f.name)
            if found is not None:
                return found
    return None


def _strings(msg: Message, path: str = "") -> Iterable[tuple[str, str]]:
    """(field path, value) of every string in ``msg``, nested ones included."""
    for f, value in msg.ListFields():
        name = f"{path}.{f.name}" if path else f.name
        if f.type == FieldDescriptor.TYPE_STRING:
            yield from ((name, v) for v in (value if f.is_repeated else [value]))
        elif f.type == FieldDescriptor.TYPE_MESSAGE and not f.message_type.GetOptions().map_entry:
            for item in value if f.is_repeated else [value]:
                yield from _strings(item, name)


def finite(values, n: int | None, name: str, bound: float | None = None) -> list[float]:
    vals = list(values)
    if n is not None and len(vals) != n:
        raise Invalid("wrong length", f"{name} has {len(vals)} values, not {n}")
    if not all(math.isfinite(v) for v in vals):
        raise Invalid("non-finite", f"{name} = {vals}")
    if bound is not None and math.sqrt(sum(v * v for v in vals)) > bound:
        raise Invalid("out of range", f"|{name}| = {math.sqrt(sum(v * v for v in vals)):.3g} > {bound:g}")
    return vals


def unit_quaternion(values, name: str) -> None:
    q = finite(values, 4, name)
    norm = math.sqrt(sum(v * v for v in q))
    if abs(norm - 1.0) > UNIT_TOLERANCE:
        raise Invalid("not a unit quaternion", f"|{name}| = {norm:.4f}")


def _same_episode(episode_id: str, ctx: Context | None, what: str) -> None:
    if ctx is not None and ctx.episode_id and episode_id and episode_id != ctx.episode_id:
        raise Invalid("another episode", f"{what} of episode {episode_id[:60]!r}, recording {ctx.episode_id!r}")


def check_action(a: EefAction, name: str = "action") -> None:
    finite(a.dp, 3, f"{name}.dp", MAX_STEP_M)
    finite(a.drot, 3, f"{name}.drot", MAX_STEP_RAD)
    if not math.isfinite(a.gripper) or not -0.01 <= a.gripper <= 1.01:
        raise Invalid("out of range", f"{name}.gripper = {a.gripper} (a closure in [0, 1])")


def jpeg_dimensions(data: bytes) -> tuple[int, int]:
    try:
        return jpeg_size(data)
    except ImageDecodeError as exc:
        raise Invalid("bad JPEG", str(exc)) from None


# -- per message type ---------------------------------------------------------------------------


def check(msg: Message, ctx: Context | None = None, decode_images: bool = True) -> None:
    """Raise ``Invalid`` unless ``msg``'s values make sense for its type (and ``ctx``)."""
    for name, value in _strings(msg):
        limit = MAX_TEXT if name.rsplit(".", 1)[-1] in TEXT_FIELDS else MAX_STRING
        if len(value) > limit:
            raise Invalid("oversized field", f"{name} holds {len(value)} characters (at most {limit})")
    if isinstance(msg, RobotState):
        finite(msg.eef_pos, 3, "eef_pos", MAX_POSITION_M)
        unit_quaternion(msg.eef_quat_wxyz, "eef_quat_wxyz")
        for name in ("joint_pos", "joint_vel"):
            if len(getattr(msg, name)) > MAX_REPEATED:
                raise Invalid("oversized field", f"{name} has {len(getattr(msg, name))} values")
            finite(getattr(msg, name), None, name)
        if not math.isfinite(msg.gripper) or not -0.01 <= msg.gripper <= 1.01:
            raise Invalid("out of range", f"gripper = {msg.gripper} (a closure in [0, 1])")
        _same_episode(msg.episode_id, ctx, "robot state")
    elif isinstance(msg, (AppliedAction, EefCommand)):
        check_action(msg.action)
        if isinstance(msg, AppliedAction):
            unknown = [x for x in msg.limits if x not in LIMITS]
            if unknown or len(msg.limits) > len(LIMITS):
                raise Invalid("out of range", f"limits {list(msg.limits)[:8]} (known: {', '.join(sorted(LIMITS))})")
    elif isinstance(msg, TaskState):
        if not msg.task:
            raise Invalid("missing field", "task state without a task")
        if len(msg.objects) > MAX_REPEATED:
            raise Invalid("oversized field", f"{len(msg.objects)} objects")
        for i, o in enumerate(msg.objects):
            finite(o.pos, 3, f"objects[{i}].pos", MAX_POSITION_M)
            unit_quaternion(o.quat_wxyz, f"objects[{i}].quat_wxyz")
        _same_episode(msg.episode_id, ctx, "task state")
    elif isinstance(msg, CompressedImage):
        if msg.format.lower() not in ("jpeg", "jpg"):
            raise Invalid("not JPEG", f"image format {msg.format!r} is not jpeg")
        check_jpeg(msg.data, decode=decode_images)
        size = ctx.image_sizes.get(msg.frame_id) if ctx is not None else None
        if size is not None:
            got = jpeg_dimensions(msg.data)
            if got != size:
                raise Invalid("wrong image size", f"{got[0]}x{got[1]} frame, {size[0]}x{size[1]} calibrated")
    elif isinstance(msg, CameraCalibration):
        if not (0 < msg.width <= MAX_IMAGE_SIDE and 0 < msg.height <= MAX_IMAGE_SIDE) or len(msg.K) != 9:
            raise Invalid("bad calibration", f"{msg.width}x{msg.height} with {len(msg.K)} K values")
        K = finite(msg.K, 9, "K")
        if K[0] <= 0 or K[4] <= 0 or K[8] != 1.0:
            raise Invalid("bad calibration", f"K = {K} (fx, fy > 0, K[2][2] = 1)")
        for name in ("D", "R", "P"):
            finite(getattr(msg, name), None, name)
    elif isinstance(msg, FrameTransform):
        t = msg.translation
        finite([t.x, t.y, t.z], 3, "translation", MAX_POSITION_M * 10)
        r = msg.rotation
        unit_quaternion([r.w, r.x, r.y, r.z], "rotation")


def check_jpeg(data: bytes, decode: bool = True) -> None:
    """Raise ``Invalid`` unless ``data`` is one complete JPEG (SOI ... EOI) that decodes."""
    if len(data) < 4 or data[:2] != b"\xff\xd8":
        raise Invalid("bad JPEG", f"image data is not a JPEG (no start-of-image marker, {len(data)} bytes)")
    # libjpeg decodes a truncated stream with only a warning, so check the end marker ourselves;
    # some camera drivers pad frames with zeros after it.
    if data.rstrip(b"\x00")[-2:] != b"\xff\xd9":
        raise Invalid("bad JPEG", f"truncated JPEG (no end-of-image marker, {len(data)} bytes)")
    if decode:
        try:
            decode_jpeg(data)
        except ImageDecodeError as exc:
            raise Invalid("bad JPEG", str(exc)) from None


def capture_ns(msg: Message) -> int:
    """Capture time of a message: ``header.stamp_ns`` or foxglove ``timestamp``."""
    if isinstance(msg, (CompressedImage, CameraCalibration, FrameTransform)):
        return msg.timestamp.ToNanoseconds()
    header = getattr(msg, "header", None)
    if isinstance(header, Header):
        return int(header.stamp_ns)
    return 0


def decode_strict(msg_type: type[Message], payload: bytes) -> Message:
    """``payload`` as ``msg_type`` with no field its schema does not know; ``Invalid`` otherwise."""
    msg = msg_type()
    try:
        msg.ParseFromString(payload)
    except DecodeError as exc:
        raise Invalid("undecodable", f"not a valid {msg.DESCRIPTOR.full_name}: {exc}") from None
    unknown = _unknown_field_path(msg)
    if unknown is not None:
        raise Invalid("wrong schema", f"fields unknown to {msg.DESCRIPTOR.full_name} in {unknown}")
    return msg


def parse(topic: Topic, payload: bytes, decode_images: bool = True, ctx: Context | None = None) -> Message:
    """Decode and check ``payload`` for ``topic``; raise ``Invalid`` with the reason."""
    msg = decode_strict(topic.msg_type, payload)
    if capture_ns(msg) <= 0:
        raise Invalid("no capture time", f"{msg.DESCRIPTOR.full_name} carries no capture time")
    check(msg, ctx, decode_images)
    return msg


# -- control requests ---------------------------------------------------------------------------


def check_episode_request(req: EpisodeRequest, max_ticks: int) -> None:
    """An EpisodeRequest's values (its type was checked by ``decode_strict``)."""
    if req.command not in EpisodeCommand.values() or req.command == EpisodeCommand.EPISODE_COMMAND_UNSPECIFIED:
        raise Invalid("bad request", f"unknown episode command {req.command}")
    for name, value in _strings(req):
        if len(value) > MAX_STRING:
            raise Invalid("oversized field", f"{name} holds {len(value)} characters (at most {MAX_STRING})")
    if req.command == EpisodeCommand.EPISODE_COMMAND_START:
        if not math.isfinite(req.control_hz) or not 0 <= req.control_hz <= 10_000:
            raise Invalid("out of range", f"control_hz = {req.control_hz}")
    if req.ticks > max_ticks:
        raise Invalid("out of range", f"ticks = {req.ticks} (an episode holds at most {max_ticks})")


def check_sim_request(req: SimControlRequest, tasks: Iterable[str]) -> None:
    if req.command not in SimCommand.values() or req.command == SimCommand.SIM_COMMAND_UNSPECIFIED:
        raise Invalid("bad request", f"unknown sim command {req.command}")
    if req.task and req.task not in tasks:
        raise Invalid("bad request", f"unknown task {req.task[:40]!r}; tasks: {', '.join(tasks)}")
    if len(req.episode_id) > MAX_STRING:
        raise Invalid("oversized field", f"episode_id holds {len(req.episode_id)} characters")


def counts_by_reason(counts: Mapping[tuple[str, str], int]) -> dict[str, int]:
    """{(topic, reason): n} -> {"topic: reason": n} (the EpisodeMeta map)."""
    return {f"{k}: {r}": n for (k, r), n in sorted(counts.items()) if n}
