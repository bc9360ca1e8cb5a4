import numpy as np
import pytest

from services.core.tensors import ImageDecodeError, decode_jpeg, encode_jpeg, from_tensor, to_tensor
from services.pb.common_pb2 import Tensor


@pytest.mark.parametrize("dtype", ["float32", "float64", "uint8", "int64"])
def test_tensor_round_trip_keeps_shape_dtype_and_values(dtype):
    a = (np.arange(24).reshape(2, 3, 4) * 1.5).astype(dtype)
    wire = Tensor.FromString(to_tensor(a[:, ::2]).SerializeToString())  # non-contiguous input
    b = from_tensor(wire)
    assert b.dtype == a.dtype and b.shape == (2, 2, 4)
    assert np.array_equal(b, a[:, ::2])


def test_tensor_with_wrong_byte_count_is_refused():
    msg = to_tensor(np.zeros((2, 3), np.float32))
    msg.data = msg.data[:-1]
    with pytest.raises(ValueError, match="needs 24 bytes, got 23"):
        from_tensor(msg)


def test_jpeg_round_trip_and_garbage():
    rgb = np.zeros((16, 24, 3), np.uint8)
    rgb[:, :12] = (255, 0, 0)  # left half red: channel order must survive
    back = decode_jpeg(encode_jpeg(rgb, quality=95))
    assert back.shape == rgb.shape
    assert back[8, 4, 0] > 200 and back[8, 4, 2] < 50 and back[8, 20].max() < 50
    with pytest.raises(ImageDecodeError):
        decode_jpeg(b"\xff\xd8 not a jpeg")
    with pytest.raises(ImageDecodeError):
        decode_jpeg(b"PNG")
