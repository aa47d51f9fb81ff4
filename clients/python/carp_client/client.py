"""`PolicyClient`: one robot's connection to `carp serve`, with timeouts and bounded reconnection.

Each `infer` sends one step's observation and blocks until the action chunk arrives or `timeout` passes; the server
keeps the observation history (its last `To` steps) per connection. A lost connection is reopened with exponential
back-off, a bounded number of times; the new connection starts a new episode on the server (its history is empty
again), as it would after `reset`.
"""

from __future__ import annotations

import time
from typing import Any

from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus
from websockets.sync.client import ClientConnection, connect

from carp_client.wire import decode, encode

SPEC_KEYS = (
    "observation", "observation_keys", "obs_steps", "action", "executed_offset", "action_steps", "control_period_s"
)  # fmt: skip
"""The metadata entries that say what a request holds and how to execute a reply."""


class ServerError(RuntimeError):
    """The server answered a request with an error line (e.g. ``obs: expected shape (3,), got (4,)``)."""


class SpecChangedError(ConnectionError):
    """The server now serves a policy with another observation or action spec; read `PolicyClient.metadata` again.

    The server closes every connection when a reload changes the spec; the client reconnects, finds the new
    metadata and raises this instead of sending the old kind of request.
    """


class PolicyClient:
    """A blocking client of one policy server; use it as a context manager.

    Args:
        url: ``ws://host:port`` of the server.
        token: bearer token when the server requires one.
        timeout: seconds to wait for the opening handshake, the metadata frame and each reply.
        connect_attempts: connection attempts before giving up (at start and after a lost connection).
        initial_backoff_s: wait after the first failed attempt; doubled after each further one.
        max_backoff_s: the longest wait between two attempts.
    """

    def __init__(
        self,
        url: str = "ws://127.0.0.1:8000",
        token: str | None = None,
        timeout: float = 10.0,
        connect_attempts: int = 5,
        initial_backoff_s: float = 0.1,
        max_backoff_s: float = 2.0,
    ) -> None:
        if connect_attempts < 1:
            raise ValueError(f"connect_attempts must be >= 1, got {connect_attempts}")
        self.url = url
        self.token = token
        self.timeout = timeout
        self.connect_attempts = connect_attempts
        self.initial_backoff_s = initial_backoff_s
        self.max_backoff_s = max_backoff_s
        self._connection: ClientConnection | None = None
        self._metadata: dict[str, Any] | None = None
        self._step = 0
        self._reset_seed: int | None = None

    @property
    def metadata(self) -> dict[str, Any]:
        """The server's metadata frame: observation and action specs, `obs_steps`, `action_steps`, the model."""
        if self._metadata is None:
            self.connect()
        return self._metadata

    def connect(self) -> None:
        """Open the connection and read the metadata frame, retrying with back-off.

        Raises:
            PermissionError: the server refused the token (HTTP 401 or 403).
            TimeoutError: the last attempt timed out (a server that accepts connections but does not answer).
            ConnectionError: every attempt failed otherwise.
        """
        self.close()
        delay = self.initial_backoff_s
        for attempt in range(1, self.connect_attempts + 1):
            try:
                self._open()
                return
            except InvalidStatus as error:
                status = error.response.status_code
                if status in (401, 403):
                    raise PermissionError(f"{self.url} refused the connection: HTTP {status}") from None
                failure: Exception = error
            except (OSError, TimeoutError, InvalidHandshake, ConnectionClosed) as error:
                failure = error
            if attempt < self.connect_attempts:
                time.sleep(delay)
                delay = min(2 * delay, self.max_backoff_s)
        message = f"could not connect to {self.url} in {self.connect_attempts} attempts: {failure}"
        if isinstance(failure, TimeoutError):
            raise TimeoutError(message) from failure
        raise ConnectionError(message) from failure

    def _open(self) -> None:
        headers = {"Authorization": "Bearer " + self.token} if self.token else None
        # The connection outlives this call, so no `with` block; entering it by hand is what websockets >= 17.1 asks
        # of such a connection (its `legacy=True` does not exist in the older versions the client supports).
        connection = connect(
            self.url,
            additional_headers=headers,
            open_timeout=self.timeout,
            close_timeout=self.timeout,
            compression=None,
        ).__enter__()
        try:
            frame = connection.recv(timeout=self.timeout)
            if isinstance(frame, str):
                raise ServerError(frame)
            self._metadata = decode(frame)
        except BaseException:
            connection.close()
            raise
        self._connection = connection

    def reset(self, seed: int = 0) -> None:
        """Start a new episode with the next `infer`, whose random draws on the server come from `seed`."""
        self._reset_seed = seed

    def infer(self, obs: dict[str, Any]) -> dict[str, Any]:
        """Send one step's observation; return the server's reply.

        Args:
            obs: ``obs`` (Do,) float32, or one (width,) float32 array per low-dim key under its name (the
                metadata's ``observation_keys``, when the server lists them), and for an image policy ``images``
                (cameras, 3, h, w) uint8 (see the metadata's ``observation``); ``step`` and ``timestamp`` are added
                unless given.

        Returns:
            ``actions`` (H, A) float32 (execute rows ``executed_offset`` to ``executed_offset + action_steps``),
            ``step``, ``timestamp``, ``model_version`` and ``timing_ms``.

        Raises:
            ServerError: the server rejected the request (the connection stays usable).
            SpecChangedError: the server swapped in a policy with another spec (the metadata is the new one).
            TimeoutError: no reply within `timeout`; the connection is dropped and reopened by the next call.
            ConnectionError, PermissionError: the connection was lost and could not be reopened.
        """
        request = dict(obs)
        request.setdefault("step", self._step)
        request.setdefault("timestamp", time.time())
        if self._reset_seed is not None:
            request.update(reset=True, seed=self._reset_seed)
        frame = encode(request)
        for attempt in range(2):
            if self._connection is None:
                known = self._metadata
                self.connect()
                if known is not None and _spec(known) != _spec(self._metadata):
                    raise SpecChangedError(
                        f"{self.url} now serves a policy with another observation or action spec: read the metadata "
                        "again and build the requests from it"
                    )
            try:
                self._connection.send(frame)
                reply = self._connection.recv(timeout=self.timeout)
                break
            except TimeoutError:
                # A late reply would answer the next request: this connection is out of step, so it goes.
                self.close()
                raise TimeoutError(f"no reply from {self.url} within {self.timeout} s") from None
            except ConnectionClosed:
                self.close()
                if attempt == 1:
                    raise ConnectionError(f"{self.url} closed the connection twice in a row") from None
        if isinstance(reply, str):
            raise ServerError(reply)
        self._step += 1
        self._reset_seed = None
        return decode(reply)

    def observe(self, obs: dict[str, Any]) -> dict[str, Any]:
        """Send one step's observation for the history only (no chunk is predicted); return the server's reply.

        A robot that executes several actions of a chunk sends the steps in between this way, so that the server's
        history holds the last `To` steps when `infer` asks for the next chunk. Arguments and errors as `infer`;
        the reply has ``step``, ``timestamp`` and ``model_version``.
        """
        return self.infer({**obs, "predict": False})

    def close(self) -> None:
        """Close the connection (the next call reopens it)."""
        if self._connection is not None:
            self._connection.close()
            self._connection = None

    def __enter__(self) -> PolicyClient:
        self.connect()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _spec(metadata: dict[str, Any]) -> dict[str, Any]:
    return {key: metadata.get(key) for key in SPEC_KEYS}
