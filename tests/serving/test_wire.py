import msgpack
import numpy as np
import pytest
from carp_client import wire as client_wire

from carp.serving import wire

MESSAGES = [
    {"obs": np.arange(3, dtype=np.float32), "step": 4, "timestamp": 1.5, "reset": True},
    {"images": np.zeros((2, 3, 4, 4), np.uint8), "nested": [np.ones((2, 2)), {"mask": np.array([True, False])}]},
    {"actions": np.linspace(-1, 1, 16, dtype=np.float32).reshape(8, 2), "model_version": "abc", "seed": np.int64(3)},
]


@pytest.mark.parametrize("message", MESSAGES)
def test_server_and_client_codecs_write_the_same_bytes_and_read_each_other(message):
    frame = wire.encode(message)
    assert client_wire.encode(message) == frame
    for decoded in (wire.decode(frame), client_wire.decode(frame)):
        assert decoded.keys() == message.keys()
    decoded = wire.decode(frame)
    for key, value in message.items():
        if isinstance(value, np.ndarray):
            assert decoded[key].dtype == value.dtype
            np.testing.assert_array_equal(decoded[key], value)


def test_arrays_use_openpis_binary_keys_and_text_keys_are_read_too():
    array = np.arange(6, dtype=np.float32).reshape(2, 3)
    raw = msgpack.unpackb(wire.encode({"obs": array}), raw=False)
    assert raw["obs"] == {b"__ndarray__": True, b"data": array.tobytes(), b"dtype": "<f4", b"shape": [2, 3]}
    text_keys = {"__ndarray__": True, "data": array.tobytes(), "dtype": "<f4", "shape": [2, 3]}
    np.testing.assert_array_equal(wire.decode(msgpack.packb({"obs": text_keys}))["obs"], array)


@pytest.mark.parametrize(
    "frame, words",
    [
        (b"\xc1", "not a msgpack message"),
        (b"\x93\x01", "not a msgpack message"),
        (msgpack.packb(msgpack.ExtType(1, b"x")), "extension type"),
        (msgpack.packb({"a": {"__ndarray__": True, "data": b"xx", "dtype": "<f4", "shape": [1]}}), "needs 4 bytes"),
        (msgpack.packb({"a": {"__ndarray__": True, "data": b"x" * 8, "dtype": "|O", "shape": [1]}}), "not accepted"),
        (msgpack.packb({"a": {"__ndarray__": True, "data": b"", "dtype": "<f4", "shape": [-1]}}), "non-negative"),
    ],
)
def test_invalid_frames_raise_wire_errors(frame, words):
    with pytest.raises(wire.WireError, match=words):
        wire.decode(frame)


def test_object_arrays_are_not_sent():
    with pytest.raises(TypeError, match="dtype object"):
        wire.encode({"obs": np.array([object()])})
