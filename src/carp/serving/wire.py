"""The serving wire format: msgpack frames in which numpy arrays travel as tagged maps.

An array is packed as the map ``{b"__ndarray__": True, b"data": <raw bytes>, b"dtype": <numpy dtype .str>,
b"shape": [...]}``: the convention of openpi's `msgpack_numpy` (whose keys are msgpack binary strings), so an
unmodified openpi client can drive a carp server and read its replies. Decoding also accepts the same map with text
keys, and openpi's numpy scalar map ``{b"__npgeneric__": True, b"data": <number>, b"dtype": <dtype .str>}`` (an
``np.int64`` step, for instance), which becomes the plain Python number. Deviations from openpi: numpy scalars are
sent as plain msgpack numbers, only boolean, integer and floating-point arrays and scalars are accepted, and a
decoded array is checked against its declared size.

Nothing here unpickles: msgpack holds only plain values, and extension types (msgpack's Timestamp, type -1,
included) are refused. Before msgpack builds any object, :func:`check_structure` walks the frame's headers and
refuses one with more than `max_objects` values or nested deeper than `max_depth`: a frame's bytes alone do not bound
the work of decoding it (a 1 MiB frame can hold a million empty maps, each one a Python object and a call of the
array hook), and the walk stops at the first value past the budget. The robot-side client
(`clients/python/carp_client/wire.py`) keeps its own copy of the codec for the frames it trusts (the server's
replies), so that it never imports carp; a test checks that the two produce the same bytes.
"""

from typing import Any

import msgpack
import numpy as np

ARRAY_KINDS = "biuf"
"""numpy dtype kinds an array on the wire may have: bool, signed and unsigned integers, floating point."""
DEFAULT_MAX_OBJECTS = 1024
"""Values (containers, keys and scalars) in one request frame: a request of every observation key with its array
maps holds about a hundred (Lift's four keys: 60); 1024 bounds a hostile frame's decoding to about half a
millisecond."""
DEFAULT_MAX_DEPTH = 16
"""Containers nested in one request frame: a request is a map of maps (array maps, openpi's nested observations)."""

_FIXED_SIZES = {
    0xC0: 0, 0xC2: 0, 0xC3: 0,  # nil, false, true
    0xCA: 4, 0xCB: 8,  # float32, float64
    0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8,  # uint8 to uint64
    0xD0: 1, 0xD1: 2, 0xD2: 4, 0xD3: 8,  # int8 to int64
}  # fmt: skip
"""Payload bytes after the type byte of the scalar types whose size the type byte fixes."""
_SIZED = {0xC4: 1, 0xC5: 2, 0xC6: 4, 0xD9: 1, 0xDA: 2, 0xDB: 4}
"""bin8/16/32 and str8/16/32: bytes of the big-endian length that follows the type byte."""
_CONTAINERS = {0xDC: (2, 1), 0xDD: (4, 1), 0xDE: (2, 2), 0xDF: (4, 2)}
"""array16/32, map16/32: bytes of the big-endian count, and values per counted element (a map's key and value)."""
_EXTENSIONS = {0xC7: 1, 0xC8: 2, 0xC9: 4, 0xD4: 0, 0xD5: 0, 0xD6: 0, 0xD7: 0, 0xD8: 0}
"""ext8/16/32 and fixext1 to 16: bytes of the length before the extension's type code."""


class WireError(ValueError):
    """A frame that is not a valid message: not msgpack, or an array map that does not describe an array."""


def check_structure(frame: bytes, max_objects: int = DEFAULT_MAX_OBJECTS, max_depth: int = DEFAULT_MAX_DEPTH) -> None:
    """Refuse `frame` unless it is one msgpack value of at most `max_objects` values nested at most `max_depth` deep.

    Reads only the type bytes and lengths (msgpack's format: github.com/msgpack/msgpack, spec.md), so its cost is
    proportional to the values it reads, never more than `max_objects`.

    Raises:
        WireError: too many values, too deep, an extension type, a reserved or truncated header, or bytes after
            the value.
    """
    end = len(frame)
    position = objects = 0
    pending = [1]  # values still to read in each open container, outermost first; the frame is one value
    while pending:
        if pending[-1] == 0:
            pending.pop()
            continue
        pending[-1] -= 1
        if position >= end:
            raise WireError("not a msgpack message (truncated)")
        objects += 1
        if objects > max_objects:
            raise WireError(f"more than {max_objects} values in one frame")
        byte = frame[position]
        position += 1
        children = 0
        if byte <= 0x7F or byte >= 0xE0:
            continue  # positive and negative fixint
        if byte <= 0x8F:
            children = 2 * (byte & 0x0F)  # fixmap
        elif byte <= 0x9F:
            children = byte & 0x0F  # fixarray
        elif byte <= 0xBF:
            position += byte & 0x1F  # fixstr
        elif byte in _FIXED_SIZES:
            position += _FIXED_SIZES[byte]
        elif byte in _SIZED:
            width = _SIZED[byte]
            position += width + int.from_bytes(frame[position : position + width], "big")
        elif byte in _CONTAINERS:
            width, per_element = _CONTAINERS[byte]
            children = per_element * int.from_bytes(frame[position : position + width], "big")
            position += width
        elif byte in _EXTENSIONS:
            width = _EXTENSIONS[byte]
            code = frame[position + width] if position + width < end else 0
            raise WireError(f"msgpack extension type {code - 256 if code > 127 else code} is not accepted")
        else:
            raise WireError(f"not a msgpack message (reserved type byte 0x{byte:02x})")
        if position > end:
            raise WireError("not a msgpack message (truncated)")
        if children:
            pending.append(children)
            if len(pending) - 1 > max_depth:
                raise WireError(f"values nested more than {max_depth} deep")
    if position != end:
        raise WireError("not a msgpack message (bytes after the value)")


def _pack_array(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in ARRAY_KINDS:
            raise TypeError(f"arrays of dtype {value.dtype} cannot be sent")
        return {b"__ndarray__": True, b"data": value.tobytes(), b"dtype": value.dtype.str, b"shape": list(value.shape)}
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} cannot be sent")


def _field(tagged: dict, name: str) -> Any:
    return tagged[name.encode()] if name.encode() in tagged else tagged.get(name)


def _dtype(dtype_name: Any) -> np.dtype:
    if not isinstance(dtype_name, str):
        raise WireError(f"dtype {dtype_name!r} is not a string")
    try:
        dtype = np.dtype(dtype_name)
    except TypeError:
        raise WireError(f"unknown dtype {dtype_name!r}") from None
    if dtype.kind not in ARRAY_KINDS:
        raise WireError(f"dtype {dtype_name!r} is not accepted (bool, integer or floating point only)")
    return dtype


def _unpack_scalar(tagged: dict) -> Any:
    """The plain Python number an openpi numpy scalar map holds, after checking that its dtype holds it."""
    data, dtype = _field(tagged, "data"), _dtype(_field(tagged, "dtype"))
    if isinstance(data, bool) != (dtype.kind == "b") or not isinstance(data, int | float):
        raise WireError(f"scalar map of dtype {dtype.str} holds {type(data).__name__}")
    if isinstance(data, float) and dtype.kind != "f":
        raise WireError(f"scalar map of dtype {dtype.str} holds a float")
    if dtype.kind in "iu" and not np.iinfo(dtype).min <= data <= np.iinfo(dtype).max:
        raise WireError(f"scalar map of dtype {dtype.str} holds {data}, out of its range")
    return dtype.type(data).item()


def _unpack_array(tagged: dict) -> Any:
    if _field(tagged, "__npgeneric__") is True:
        return _unpack_scalar(tagged)
    if _field(tagged, "__ndarray__") is not True:
        return tagged
    data, dtype_name, shape = _field(tagged, "data"), _field(tagged, "dtype"), _field(tagged, "shape")
    if not isinstance(data, bytes) or not isinstance(dtype_name, str) or not isinstance(shape, list):
        raise WireError("array map needs data (bytes), dtype (str) and shape (list)")
    try:
        dtype = _dtype(dtype_name)
    except WireError as error:
        raise WireError(f"array {error}") from None
    if not all(isinstance(size, int) and not isinstance(size, bool) and size >= 0 for size in shape):
        raise WireError(f"array shape {shape} is not a list of non-negative integers")
    expected = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if len(data) != expected:
        raise WireError(f"array of shape {tuple(shape)} and dtype {dtype_name} needs {expected} bytes, got {len(data)}")
    return np.frombuffer(data, dtype=dtype).reshape(shape)


def _refuse_extension(code: int, data: bytes) -> Any:
    raise WireError(f"msgpack extension type {code} is not accepted")


def encode(message: Any) -> bytes:
    """One msgpack frame of `message` (dicts, lists, numbers, strings, bytes, numpy arrays and scalars).

    Raises:
        TypeError: a value that has no wire form (an object array, an arbitrary object).
    """
    return msgpack.packb(message, default=_pack_array, use_bin_type=True)


def decode(frame: bytes, max_objects: int = DEFAULT_MAX_OBJECTS, max_depth: int = DEFAULT_MAX_DEPTH) -> Any:
    """The message a msgpack frame holds; array maps become read-only numpy arrays, scalar maps plain numbers.

    Args:
        frame: the frame's bytes.
        max_objects: most values (containers, keys, scalars) the frame may hold (:func:`check_structure`).
        max_depth: most containers nested in one another.

    Raises:
        WireError: the frame is not one msgpack value, exceeds the limits, or holds an invalid array or scalar map
            or an extension type.
    """
    check_structure(frame, max_objects, max_depth)
    try:
        # max_ext_len=0 also refuses the Timestamp type, which msgpack decodes itself without asking `ext_hook`.
        return msgpack.unpackb(
            frame, object_hook=_unpack_array, ext_hook=_refuse_extension, raw=False, max_ext_len=0, strict_map_key=False
        )
    except WireError:
        raise
    except (ValueError, TypeError, msgpack.UnpackException) as error:
        raise WireError(f"not a msgpack message ({type(error).__name__})") from None
