"""The serving wire format, the client's own copy (it must not import carp): msgpack with tagged numpy arrays.

An array travels as ``{b"__ndarray__": True, b"data": <raw bytes>, b"dtype": <numpy dtype .str>, b"shape": [...]}``,
openpi's `msgpack_numpy` convention; numpy scalars travel as plain numbers. `carp.serving.wire` is the server's copy;
a test in carp checks that both produce the same bytes.
"""

from typing import Any

import msgpack
import numpy as np

ARRAY_KINDS = "biuf"


class WireError(ValueError):
    """A frame that is not a valid message."""


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
    dtype = np.dtype(dtype_name)
    if dtype.kind not in ARRAY_KINDS or len(data) != int(np.prod(shape, dtype=np.int64)) * dtype.itemsize:
        raise WireError(f"array map of dtype {dtype_name} and shape {shape} does not hold such an array")
    return np.frombuffer(data, dtype=dtype).reshape(shape)


def encode(message: Any) -> bytes:
    """One msgpack frame of `message` (dicts, lists, numbers, strings, bytes, numpy arrays and scalars)."""
    return msgpack.packb(message, default=_pack_array, use_bin_type=True)


def decode(frame: bytes) -> Any:
    """The message a msgpack frame holds; array maps become read-only numpy arrays."""
    return msgpack.unpackb(frame, object_hook=_unpack_array, raw=False)
