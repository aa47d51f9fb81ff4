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


def test_msgpack_timestamps_are_refused_like_every_extension_type():
    with pytest.raises(wire.WireError, match="extension type -1 is not accepted"):
        wire.decode(msgpack.packb({"timestamp": msgpack.Timestamp(1, 0)}, datetime=False))


@pytest.mark.parametrize(
    "message, words",
    [
        ([{}] * (wire.DEFAULT_MAX_OBJECTS + 1), f"more than {wire.DEFAULT_MAX_OBJECTS} values"),
        ({"obs": [[] for _ in range(wire.DEFAULT_MAX_OBJECTS)]}, f"more than {wire.DEFAULT_MAX_OBJECTS} values"),
    ],
)
def test_a_frame_of_more_values_than_the_limit_is_refused_before_it_is_built(message, words):
    with pytest.raises(wire.WireError, match=words):
        wire.decode(msgpack.packb(message))


def test_nesting_deeper_than_the_limit_is_refused():
    nested: object = 1
    for _ in range(wire.DEFAULT_MAX_DEPTH):
        nested = [nested]
    assert wire.decode(msgpack.packb(nested)) == nested
    with pytest.raises(wire.WireError, match=f"nested more than {wire.DEFAULT_MAX_DEPTH} deep"):
        wire.decode(msgpack.packb([nested]))


def test_the_structure_check_accepts_every_msgpack_type_it_allows_and_refuses_truncations_and_extra_bytes():
    message = {
        "ints": [0, 127, 128, 255, 256, 65536, 2**32, 2**63, -1, -32, -33, -129, -32769, -(2**31) - 1, -(2**63)],
        "floats": [1.5, -0.0],
        "strings": ["", "a" * 31, "b" * 32, "c" * 256, "d" * 65536],
        "bytes": [b"", b"x" * 256, b"y" * 65536],
        "flags": [None, True, False],
        "containers": [list(range(16)), {str(key): key for key in range(16)}, [[]] * 3, {}],
    }
    frame = msgpack.packb(message, use_bin_type=True)
    wire.check_structure(frame, max_objects=10_000)
    assert wire.decode(frame, max_objects=10_000) == message
    for broken, words in ((frame[:-1], "truncated"), (frame + b"\x00", "bytes after the value")):
        with pytest.raises(wire.WireError, match=words):
            wire.check_structure(broken, max_objects=10_000)


def test_numpy_scalars_packed_as_openpi_packs_them_decode_to_plain_numbers():
    def scalar(value: np.generic) -> dict:
        return {b"__npgeneric__": True, b"data": value.item(), b"dtype": value.dtype.str}

    frame = msgpack.packb(
        {"step": scalar(np.int64(7)), "timestamp": scalar(np.float64(2.5)), "reset": scalar(np.bool_(True))}
    )
    decoded = wire.decode(frame)
    assert decoded == {"step": 7, "timestamp": 2.5, "reset": True}
    assert type(decoded["step"]) is int and type(decoded["reset"]) is bool
    for bad, words in (
        ({b"__npgeneric__": True, b"data": 300, b"dtype": "|u1"}, "out of its range"),
        ({b"__npgeneric__": True, b"data": 1.5, b"dtype": "<i8"}, "holds a float"),
        ({b"__npgeneric__": True, b"data": 1, b"dtype": "|O"}, "not accepted"),
    ):
        with pytest.raises(wire.WireError, match=words):
            wire.decode(msgpack.packb({"step": bad}))
