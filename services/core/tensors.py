"""ndarray <-> Tensor message, and JPEG <-> foxglove CompressedImage."""

from __future__ import annotations

import cv2
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

from services.pb.common_pb2 import Tensor


def to_tensor(array: np.ndarray) -> Tensor:
    array = np.ascontiguousarray(array)
    return Tensor(dtype=array.dtype.str, shape=list(array.shape), data=array.tobytes())


def from_tensor(msg: Tensor) -> np.ndarray:
    dtype = np.dtype(msg.dtype)
    shape = tuple(int(s) for s in msg.shape)
    expected = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if len(msg.data) != expected:
        raise ValueError(f"tensor of shape {shape} {dtype} needs {expected} bytes, got {len(msg.data)}")
    return np.frombuffer(msg.data, dtype=dtype).reshape(shape).copy()


def encode_jpeg(rgb: np.ndarray, quality: int = 90) -> bytes:
    """(H, W, 3) uint8 RGB -> JPEG bytes."""
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()


class ImageDecodeError(ValueError):
    pass


def decode_jpeg(data: bytes) -> np.ndarray:
    """JPEG bytes -> (H, W, 3) uint8 RGB; raises ImageDecodeError on anything undecodable."""
    if len(data) < 4 or data[:2] != b"\xff\xd8":
        raise ImageDecodeError(f"not a JPEG ({len(data)} bytes)")
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ImageDecodeError(f"undecodable JPEG ({len(data)} bytes)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def compressed_image(rgb: np.ndarray, stamp_ns: int, frame_id: str, quality: int = 90) -> CompressedImage:
    msg = CompressedImage(frame_id=frame_id, format="jpeg", data=encode_jpeg(rgb, quality))
    msg.timestamp.FromNanoseconds(stamp_ns)
    return msg
