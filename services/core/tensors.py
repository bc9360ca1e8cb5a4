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


_REDUCED = {
    8: cv2.IMREAD_REDUCED_COLOR_8,
    4: cv2.IMREAD_REDUCED_COLOR_4,
    2: cv2.IMREAD_REDUCED_COLOR_2,
    1: cv2.IMREAD_COLOR,
}


class FrameSizeError(ValueError):
    """A frame whose size is not the one its camera's calibration says (the message: WxH)."""


def decode_resized(data: bytes, size: tuple[int, int], src: tuple[int, int]) -> np.ndarray | None:
    """JPEG of ``src`` (W, H) pixels -> (H, W, 3) uint8 RGB at ``size`` (W, H); None if undecodable.

    When the source is at least twice the target, libjpeg decodes at 1/2, 1/4 or 1/8 scale
    directly (DCT scaling), which is much faster than decoding in full and shrinking. A frame
    whose size is not ``src`` raises FrameSizeError (its calibration would not fit it).
    """
    w, h = size
    factor = 1
    for f in (8, 4, 2):
        if src[0] // f >= w and src[1] // f >= h:
            factor = f
            break
    if len(data) < 4 or data[:2] != b"\xff\xd8":
        return None
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), _REDUCED[factor])
    if bgr is None:
        return None
    expect = (-(-src[0] // factor), -(-src[1] // factor))  # libjpeg rounds scaled sizes up
    if (bgr.shape[1], bgr.shape[0]) != expect:
        raise FrameSizeError(f"{bgr.shape[1] * factor}x{bgr.shape[0] * factor}")
    if bgr.shape[1] != w or bgr.shape[0] != h:
        bgr = cv2.resize(bgr, (w, h), interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}  # start-of-frame markers


def jpeg_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a JPEG's frame header, without decoding it; ImageDecodeError if none."""
    if len(data) < 4 or data[:2] != b"\xff\xd8":
        raise ImageDecodeError(f"not a JPEG ({len(data)} bytes)")
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            raise ImageDecodeError(f"corrupt JPEG marker at byte {i}")
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        length = int.from_bytes(data[i + 2 : i + 4], "big")
        if marker in _SOF and i + 9 <= len(data):
            return int.from_bytes(data[i + 7 : i + 9], "big"), int.from_bytes(data[i + 5 : i + 7], "big")
        if marker in (0xD9, 0xDA) or length < 2:  # end of image or start of scan before any frame header
            break
        i += 2 + length
    raise ImageDecodeError(f"JPEG without a frame header ({len(data)} bytes)")


def compressed_image(rgb: np.ndarray, stamp_ns: int, frame_id: str, quality: int = 90) -> CompressedImage:
    msg = CompressedImage(frame_id=frame_id, format="jpeg", data=encode_jpeg(rgb, quality))
    msg.timestamp.FromNanoseconds(stamp_ns)
    return msg
