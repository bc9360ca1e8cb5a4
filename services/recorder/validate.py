"""Payload checks: what the recorder refuses to write, and why.

A payload is good when it parses as its topic's message type with no field the schema does not
know (bytes of another message type nearly always leave unknown fields behind: every publisher
builds from this repository's schemas, so an unknown field means the wrong schema, not a newer
one), carries a capture time, and -- for images -- holds a complete JPEG that decodes.
"""

from __future__ import annotations

from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from google.protobuf.descriptor import FieldDescriptor
from google.protobuf.message import DecodeError, Message
from google.protobuf.unknown_fields import UnknownFieldSet

from services.core.tensors import ImageDecodeError, decode_jpeg
from services.core.topics import Topic
from services.pb.common_pb2 import Header


class MalformedPayload(ValueError):
    """A payload the recorder will not write; the message says why."""


def _unknown_field_path(msg: Message, path: str = "") -> str | None:
    """Dotted path of the first message holding fields its schema does not define."""
    if len(UnknownFieldSet(msg)):
        return path or msg.DESCRIPTOR.name
    for field, value in msg.ListFields():
        if field.type != FieldDescriptor.TYPE_MESSAGE:
            continue
        if field.message_type.GetOptions().map_entry:
            items = value.values() if field.message_type.fields_by_name["value"].message_type else []
        elif field.is_repeated:
            items = value
        else:
            items = [value]
        for item in items:
            found = _unknown_field_path(item, f"{path}.{field.name}" if path else field.name)
            if found is not None:
                return found
    return None


def capture_ns(msg: Message) -> int:
    """Capture time of a recorded message: ``header.stamp_ns`` or foxglove ``timestamp``."""
    if isinstance(msg, (CompressedImage, CameraCalibration, FrameTransform)):
        return msg.timestamp.ToNanoseconds()
    header = getattr(msg, "header", None)
    if isinstance(header, Header):
        return int(header.stamp_ns)
    return 0


def check_jpeg(data: bytes, decode: bool = True) -> None:
    """Raise ``MalformedPayload`` unless ``data`` is one complete JPEG (SOI ... EOI)."""
    if len(data) < 4 or data[:2] != b"\xff\xd8":
        raise MalformedPayload(f"image data is not a JPEG (no start-of-image marker, {len(data)} bytes)")
    # libjpeg decodes a truncated stream with only a warning, so check the end marker ourselves;
    # some camera drivers pad frames with zeros after it.
    if data.rstrip(b"\x00")[-2:] != b"\xff\xd9":
        raise MalformedPayload(f"truncated JPEG (no end-of-image marker, {len(data)} bytes)")
    if decode:
        try:
            decode_jpeg(data)
        except ImageDecodeError as exc:
            raise MalformedPayload(str(exc)) from exc


def parse(topic: Topic, payload: bytes, decode_images: bool = True) -> Message:
    """Decode and check ``payload`` for ``topic``; raise ``MalformedPayload`` with the reason."""
    msg = topic.msg_type()
    try:
        msg.ParseFromString(payload)
    except DecodeError as exc:
        raise MalformedPayload(f"not a valid {msg.DESCRIPTOR.full_name}: {exc}") from exc
    unknown = _unknown_field_path(msg)
    if unknown is not None:
        raise MalformedPayload(f"wrong schema: fields unknown to {msg.DESCRIPTOR.full_name} in {unknown}")
    if capture_ns(msg) <= 0:
        raise MalformedPayload(f"{msg.DESCRIPTOR.full_name} carries no capture time")
    if isinstance(msg, CompressedImage):
        if msg.format.lower() not in ("jpeg", "jpg"):
            raise MalformedPayload(f"image format {msg.format!r} is not jpeg")
        check_jpeg(msg.data, decode=decode_images)
    elif isinstance(msg, CameraCalibration):
        if msg.width <= 0 or msg.height <= 0 or len(msg.K) != 9:
            raise MalformedPayload(
                f"calibration needs width, height and 9 K values (got {msg.width}x{msg.height}, {len(msg.K)} K)"
            )
    return msg
