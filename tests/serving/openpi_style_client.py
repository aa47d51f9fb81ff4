"""A client written the way openpi's websocket policy client is, to drive `carp serve` as openpi's robots would.

Written from openpi's wire format (its `msgpack_numpy` conventions and its client's header), not copied: websockets'
sync client without compression or a frame size limit, ``Authorization: Api-Key <key>``, msgpack with numpy arrays
as ``__ndarray__`` maps and numpy scalars as ``__npgeneric__`` maps (binary keys, shapes as tuples), and a text
frame raised as an error.
"""

import msgpack
import numpy as np
from websockets.sync.client import connect


class OpenpiStyleClient:
    """One connection to a policy server, opened with `api_key`; the metadata frame it sent is `metadata`."""

    def __init__(self, url: str, api_key: str) -> None:
        headers = {"Authorization": f"Api-Key {api_key}"}
        # Entered by hand: the connection outlives this call (websockets >= 17.1 asks for that or a `with` block).
        self._connection = connect(url, compression=None, max_size=None, additional_headers=headers).__enter__()
        self.metadata = self._unpack(self._connection.recv(timeout=10))

    @staticmethod
    def _pack_default(value):
        if isinstance(value, np.ndarray):
            return {b"__ndarray__": True, b"data": value.tobytes(), b"dtype": value.dtype.str, b"shape": value.shape}
        if isinstance(value, np.generic):
            return {b"__npgeneric__": True, b"data": value.item(), b"dtype": value.dtype.str}
        return value

    @staticmethod
    def _unpack_hook(value):
        if b"__ndarray__" in value:
            return np.ndarray(buffer=value[b"data"], dtype=np.dtype(value[b"dtype"]), shape=value[b"shape"])
        if b"__npgeneric__" in value:
            return np.dtype(value[b"dtype"]).type(value[b"data"])
        return value

    def _unpack(self, frame: bytes):
        return msgpack.unpackb(frame, object_hook=self._unpack_hook)

    def infer(self, observation: dict) -> dict:
        self._connection.send(msgpack.packb(observation, default=self._pack_default))
        reply = self._connection.recv(timeout=10)
        if isinstance(reply, str):
            raise RuntimeError(f"error in inference server:\n{reply}")
        return self._unpack(reply)

    def close(self) -> None:
        self._connection.close()
