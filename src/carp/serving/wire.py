"""The serving wire format: msgpack frames in which numpy arrays travel as tagged maps.

An array is packed as the map ``{b"__ndarray__": True, b"data": <raw bytes>, b"dtype": <numpy dtype .str>,
b"shape": [...]}``: the convention of openpi's `msgpack_numpy` (whose keys are msgpack binary strings), so an
unmodified openpi client can drive a carp server and read its replies. Decoding also accepts the same map with text
keys. Deviations from openpi: numpy scalars are sent as plain msgpack numbers (no `__npgeneric__` maps), only
boolean, integer and floating-point arrays are accepted, and a decoded array is checked against its declared size.

Nothing here unpickles: msgpack holds only plain values, and extension types are refused. The robot-side client
(`clients/python/carp_client/wire.py`) keeps its own copy of this codec, so that it never imports carp; a test checks
that the two produce the same bytes.
"""

from typing import Any

import msgpack
import numpy as np

ARRAY_KINDS = "biuf"
"""numpy dtype kinds an array on the wire may have: bool, signed and unsigned integers, floating point."""


class WireError(ValueError):
    """A frame that is not a valid message: not msgpack, or an array map that does not describe an array."""


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


def _unpack_array(tagged: dict) -> Any:
    if _field(tagged, "__ndarray__") is not True:
        return tagged
    data, dtype_name, shape = _field(tagged, "data"), _field(tagged, "dtype"), _field(tagged, "shape")
    if not isinstance(data, bytes) or not isinstance(dtype_name, str) or not isinstance(shape, list):
        raise WireError("array map needs data (bytes), dtype (str) and shape (list)")
    try:
        dtype = np.dtype(dtype_name)
    except TypeError:
        raise WireError(f"array map has an unknown dtype {dtype_name!r}") from None
    if dtype.kind not in ARRAY_KINDS:
        raise WireError(f"array dtype {dtype_name!r} is not accepted (bool, integer or floating point only)")
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


def decode(frame: bytes) -> Any:
    """The message a msgpack frame holds; array maps become read-only numpy arrays.

    Raises:
        WireError: the frame is not one msgpack value, or holds an invalid array map or an extension type.
    """
    try:
        return msgpack.unpackb(frame, object_hook=_unpack_array, ext_hook=_refuse_extension, raw=False)
    except WireError:
        raise
    except (ValueError, TypeError, msgpack.UnpackException) as error:
        raise WireError(f"not a msgpack message ({type(error).__name__})") from None
