"""`PolicyClient`: one robot's connection to `carp serve`, with timeouts and a bounded wait for a restarting server.

Each `infer` sends one step's observation and blocks until the action chunk arrives or `timeout` passes, closing
nothing it has to wait for: a connection that timed out is dropped at once. The server keeps the observation history
(its last `To` steps) per connection. A lost connection is reopened by waiting for the server to be ready again: the
client asks its ``/readyz`` route (which answers 200 once the model is loaded and warmed up) with exponential
back-off, for at most `reconnect_budget_s` seconds in all, and opens the WebSocket once it answers. A restarted
server loads and exports its model before it is ready, which takes seconds (5 to 11 s for a Lift CARP from launch
to ready); the default budget of 30 s covers that. The new connection starts a new episode on the server (its
history is empty again), as it would after `reset`.
"""

from __future__ import annotations

import socket
import ssl
import time
import urllib.error
import urllib.request
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
        url: ``ws://host:port`` of the server, ``wss://`` for one that serves TLS.
        token: the token when the server requires one (sent as ``Authorization: Bearer <token>``).
        timeout: seconds one attempt to connect (the opening handshake and the metadata frame) may take, and the
            most one `infer` on an open connection takes from sending to raising `TimeoutError`.
        connect_attempts: most connection attempts within the budget; None for as many as it allows.
        initial_backoff_s: wait after the first failed attempt; doubled after each further one.
        max_backoff_s: the longest wait between two attempts.
        reconnect_budget_s: the most seconds `connect` spends in all (attempts and the waits between them) before
            it gives up; a server being restarted is waited for this long.
        ssl_context: TLS settings for a ``wss://`` server, e.g. ``ssl.create_default_context(cafile=...)`` for a
            certificate no public authority signed; None for the system's defaults.
    """

    def __init__(
        self,
        url: str = "ws://127.0.0.1:8000",
        token: str | None = None,
        timeout: float = 10.0,
        connect_attempts: int | None = None,
        initial_backoff_s: float = 0.1,
        max_backoff_s: float = 2.0,
        reconnect_budget_s: float = 30.0,
        ssl_context: ssl.SSLContext | None = None,
    ) -> None:
        if connect_attempts is not None and connect_attempts < 1:
            raise ValueError(f"connect_attempts must be >= 1, got {connect_attempts}")
        if not timeout > 0 or not reconnect_budget_s > 0:
            raise ValueError(f"timeout and reconnect_budget_s must be positive, got {timeout} and {reconnect_budget_s}")
        self.url = url
        self.token = token
        self.timeout = timeout
        self.reconnect_budget_s = reconnect_budget_s
        self.connect_attempts = connect_attempts
        self.initial_backoff_s = initial_backoff_s
        self.max_backoff_s = max_backoff_s
        self.ssl_context = ssl_context
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
        """Open the connection and read the metadata frame, waiting for the server to be ready within the budget.

        After a failed attempt the client waits (with back-off) and asks ``/readyz``; when it answers 200 it opens
        the WebSocket again. Each question counts as an attempt; nothing here takes longer than
        `reconnect_budget_s` in all.

        Raises:
            PermissionError: the server refused the token (HTTP 401 or 403).
            TimeoutError: the last attempt timed out (a server that accepts connections but does not answer).
            ConnectionError: every attempt failed otherwise.
        """
        self.close()
        deadline = time.monotonic() + self.reconnect_budget_s
        delay = self.initial_backoff_s
        attempt = 0
        while True:
            attempt += 1
            remaining = deadline - time.monotonic()
            # The first attempt opens at once; later ones wait, then ask /readyz before opening.
            failure = None if attempt == 1 else self._not_ready(min(self.timeout, max(remaining, 0.001)))
            if failure is None:
                try:
                    self._open(min(self.timeout, max(deadline - time.monotonic(), 0.001)))
                    return
                except InvalidStatus as error:
                    status = error.response.status_code
                    if status in (401, 403):
                        raise PermissionError(f"{self.url} refused the connection: HTTP {status}") from None
                    failure = error
                except (OSError, TimeoutError, InvalidHandshake, ConnectionClosed) as error:
                    failure = error
            remaining = deadline - time.monotonic()
            if (self.connect_attempts is not None and attempt >= self.connect_attempts) or remaining <= 0:
                break
            time.sleep(min(delay, remaining))
            delay = min(2 * delay, self.max_backoff_s)
        message = (
            f"could not connect to {self.url} in {attempt} attempts within {self.reconnect_budget_s:g} s: {failure}"
        )
        if isinstance(failure, TimeoutError):
            raise TimeoutError(message) from failure
        raise ConnectionError(message) from failure

    def _not_ready(self, timeout: float) -> Exception | None:
        """None when ``/readyz`` answers 200 within `timeout` seconds, else why not."""
        scheme, _, rest = self.url.partition("://")
        address = rest.split("/", 1)[0]
        request = urllib.request.Request(f"{'https' if scheme == 'wss' else 'http'}://{address}/readyz")
        if self.token:
            request.add_header("Authorization", "Bearer " + self.token)
        try:
            with urllib.request.urlopen(request, timeout=timeout, context=self.ssl_context) as response:
                return None if response.status == 200 else ConnectionError(f"/readyz answered {response.status}")
        except urllib.error.HTTPError as error:
            # A refused token: the WebSocket attempt that follows says so.
            return None if error.code in (401, 403) else ConnectionError(f"/readyz answered HTTP {error.code}")
        except TimeoutError as error:
            return error
        except (OSError, ValueError) as error:
            reason = getattr(error, "reason", None)
            return reason if isinstance(reason, TimeoutError) else ConnectionError(str(error))

    def _open(self, timeout: float) -> None:
        headers = {"Authorization": "Bearer " + self.token} if self.token else None
        started = time.monotonic()
        options = {"ssl": self.ssl_context} if self.ssl_context is not None else {}
        # The connection outlives this call, so no `with` block; entering it by hand is what websockets >= 17.1 asks
        # of such a connection (its `legacy=True` does not exist in the older versions the client supports).
        connection = connect(
            self.url,
            additional_headers=headers,
            open_timeout=timeout,
            close_timeout=timeout,
            compression=None,
            **options,
        ).__enter__()
        try:
            frame = connection.recv(timeout=max(timeout - (time.monotonic() - started), 0.001))
            if isinstance(frame, str):
                raise ServerError(frame)
            self._metadata = decode(frame)
        except BaseException:
            _drop(connection)
            raise
        self._connection = connection

    def reset(self, seed: int = 0) -> None:
        """Start a new episode with the next `infer`, whose random draws on the server come from `seed`."""
        self._reset_seed = seed

    def infer(self, obs: dict[str, Any]) -> dict[str, Any]:
        """Send one step's observation; return the server's reply.

        On an open connection the call returns or raises within `timeout` seconds. Without one (the first call
        after a lost connection) it first reconnects, as `connect` does, within `reconnect_budget_s`.

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
            TimeoutError: no reply within `timeout`; the connection is dropped at once and reopened by the next call.
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
            deadline = time.monotonic() + self.timeout
            try:
                self._connection.send(frame)
                reply = self._connection.recv(timeout=max(deadline - time.monotonic(), 0.001))
                break
            except TimeoutError:
                # A late reply would answer the next request: this connection is out of step, so it goes, without
                # a closing handshake that a hung server would make us wait for.
                self._drop()
                raise TimeoutError(f"no reply from {self.url} within {self.timeout} s") from None
            except (ConnectionClosed, OSError):
                self._drop()
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

    def _drop(self) -> None:
        """Forget the connection without waiting for the server (it may be the reason for dropping it)."""
        if self._connection is not None:
            connection, self._connection = self._connection, None
            _drop(connection)

    def close(self) -> None:
        """Close the connection with a closing handshake (the next call reopens it); waits at most `timeout`."""
        if self._connection is not None:
            connection, self._connection = self._connection, None
            connection.close_timeout = min(self.timeout, 2.0)
            connection.close()

    def __enter__(self) -> PolicyClient:
        self.connect()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _drop(connection: ClientConnection) -> None:
    """Shut the connection's socket, then close it: with the socket shut, closing waits for nothing."""
    try:
        connection.socket.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    connection.close()


def _spec(metadata: dict[str, Any]) -> dict[str, Any]:
    return {key: metadata.get(key) for key in SPEC_KEYS}
