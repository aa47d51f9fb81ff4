"""Robot-side client of `carp serve`: numpy observations in, action chunks out, over WebSocket and msgpack.

Depends on numpy, msgpack and websockets only; it never imports torch or carp.
"""

from carp_client.client import PolicyClient, ServerError, SpecChangedError
from carp_client.scheduler import ChunkScheduler, ensemble_weights
from carp_client.wire import WireError, decode, encode

__all__ = [
    "ChunkScheduler",
    "PolicyClient",
    "ServerError",
    "SpecChangedError",
    "WireError",
    "decode",
    "encode",
    "ensemble_weights",
]
