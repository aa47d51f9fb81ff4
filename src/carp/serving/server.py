"""The policy server: one WebSocket port that answers observation frames with action chunks, plus plain HTTP routes.

Protocol (version `PROTOCOL_VERSION`), in `carp.serving.wire` frames:

1. On connect the server sends one metadata frame (:meth:`PolicyServer.metadata`): protocol, model, policy family,
   observation and action specs (``observation_keys``: each low-dim key's shape, when a request may send them one
   by one), control period, the executed-action offset `To - 1` and `Ta`.
2. Then each request (`carp.serving.session`) gets exactly one reply, in order: a binary frame
   ``{"actions": (H, A) float32, "step", "timestamp", "model_version", "batch_size", "timing_ms": {"queue",
   "inference", "encoding"}}``, or a text frame with one line naming the offending key (``obs: expected shape
   (3,), got (4,)``). A request with ``predict: false`` gets the same reply without ``actions``, ``batch_size`` and
   ``timing_ms`` (it only adds its observation to the history). A bad request changes nothing and the connection
   stays open. Text for errors is openpi's convention too: its client raises on a text frame.

The same port answers HTTP GET ``/healthz`` (the process is up), ``/readyz`` (200 once the model is warmed up,
503 before), ``/metadata`` (JSON) and ``/metrics`` (Prometheus text) through websockets' `process_request` hook.
With a token every route but ``/healthz``, and the WebSocket upgrade, need ``Authorization: Bearer <token>`` (or
openpi's ``Api-Key <token>``; the scheme in any case, as HTTP has it); others get 401 before any WebSocket frame is
exchanged, and a request with several ``Authorization`` headers gets 400. With a certificate and key
(`ServerSettings.tls_certificate`) the port speaks TLS (``wss://``, ``https://``).

Decoding and validating a frame run on threads of their own (`decoding_threads`), off the event loop, and the
decoder refuses a frame with more values or deeper nesting than `carp.serving.wire` allows before building any of
it: a hostile or malformed frame costs at most about a millisecond of decoding, and its connection then waits
`refusal_pause_s` before its next frame is read, so that a flood of such frames delays nobody else's replies.
Predictions run off the event loop too (`carp.serving.batching`): a policy in PyTorch one call at a time, where the
requests that wait together share the next call when the policy draws nothing random; exported ONNX Runtime graphs
on `prediction_threads` threads at once, one request per call. Frames larger than `max_request_bytes` get an error
reply; frames beyond four times that are refused by websockets itself (`max_size`), which closes the connection with
code 1009 rather than buffer them. Health probes and the other plain routes are logged at debug level.

Reload: with a `reloader` (`carp.serving.startup.model_reloader`: the registry alias moved, or the checkpoint file
changed), :meth:`PolicyServer.reload` loads and warms the new model up beside the served one, then swaps it in
between requests: a request already waiting is answered by the model it arrived under, every later one by the new
one, and none fails. It runs every `reload_interval_s` and on SIGHUP (`serve_forever`). When the new model's spec
differs (other observation keys or widths, `To`, `H`, `A`, `Ta`), every open connection is closed with code 1012
(service restart) and a reason saying so: its history no longer fits, and the robot must reconnect and read the
metadata again (`carp_client` raises `SpecChangedError`).
"""

import asyncio
import http
import json
import logging
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict
from typing import Any

from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.datastructures import MultipleValuesError
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from carp.serving.access import ProbeQuietLogger, authorized_request, tls_context
from carp.serving.batching import PredictionQueue
from carp.serving.metrics import CONTENT_TYPE as METRICS_CONTENT_TYPE
from carp.serving.metrics import ServerMetrics
from carp.serving.model import ModelSource, ServedModel
from carp.serving.session import Observed, RequestError, ServingSpec, Session
from carp.serving.settings import (
    PROTOCOL_NAME,
    PROTOCOL_VERSION,
    SPEC_CHANGED_CLOSE_CODE,
    SPEC_CHANGED_REASON,
    ServerSettings,
)
from carp.serving.wire import WireError, decode, encode

logger = logging.getLogger(__name__)


class PolicyServer:
    """Serves one `ServedModel` at a time to any number of WebSocket clients, one `Session` each.

    Args:
        model: the loaded policy.
        spec: what its requests and replies look like.
        settings: bind address, token, frame limit, batching, reload interval.
        reloader: given the served model's source, loads the model to serve now, or returns None when it is still
            the served one (`carp.serving.startup.model_reloader`); None serves `model` for good.
    """

    def __init__(
        self,
        model: ServedModel,
        spec: ServingSpec,
        settings: ServerSettings = ServerSettings(),
        reloader: Callable[[ModelSource], tuple[ServedModel, ServingSpec] | None] | None = None,
    ) -> None:
        self.model = model
        self.spec = spec
        self.settings = settings
        self.reloader = reloader
        self.metrics = ServerMetrics()
        self.ready = False
        threads = settings.prediction_threads or os.cpu_count() or 1
        self._executor = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="carp-serving")
        self._decoder = ThreadPoolExecutor(max_workers=settings.decoding_threads, thread_name_prefix="carp-decoding")
        self._queue = PredictionQueue(
            self._executor, settings.max_batch_size, self._count_call, threads, settings.batch_window_s
        )
        self._sessions: dict[ServerConnection, Session] = {}
        self._reload_lock: asyncio.Lock | None = None
        self._poller: asyncio.Task | None = None

    def metadata(self) -> dict[str, Any]:
        """The frame sent on connect and served at `/metadata`: plain values only (JSON and msgpack alike)."""
        spec = self.spec
        return {
            "protocol": PROTOCOL_NAME,
            "protocol_version": PROTOCOL_VERSION,
            "model": asdict(self.model.source),
            "model_version": self.model.source.model_version,
            "policy_type": self.model.policy.policy_type,
            "policy_description": self.model.policy.description,
            "inference": dict(self.model.inference),
            "backend": self.model.backend,
            "task": self.model.task,
            "observation": spec.observation_spec(),
            "observation_keys": spec.key_spec(),
            "obs_steps": spec.obs_steps,
            "action": {"shape": [spec.action_horizon, spec.action_dim], "dtype": "float32"},
            "control_period_s": spec.control_period_s,
            "executed_offset": spec.executed_offset,
            "action_steps": spec.action_steps,
            "max_request_bytes": self.settings.max_request_bytes,
        }

    @property
    def scheme(self) -> str:
        """``wss`` when the server speaks TLS, else ``ws``."""
        return "ws" if self.settings.tls_certificate is None else "wss"

    async def start(self) -> Server:
        """Bind, then warm the model up off the event loop; `/readyz` answers 200 from then on.

        Raises:
            OSError: the address cannot be bound.
            ValueError: the warm-up prediction does not fit the spec (the server is closed again).
        """
        tls = None
        if self.settings.tls_certificate is not None:
            tls = tls_context(self.settings.tls_certificate, self.settings.tls_key)
        server = await serve(
            self._handle,
            self.settings.host,
            self.settings.port,
            process_request=self._process_request,
            max_size=4 * self.settings.max_request_bytes,
            # Raw float and image bytes compress poorly; deflate would only add latency.
            compression=None,
            ssl=tls,
            logger=ProbeQuietLogger(logging.getLogger("websockets.server"), {}),
        )
        try:
            await asyncio.get_running_loop().run_in_executor(self._executor, self.model.warm_up, self.spec)
        except BaseException:
            server.close()
            await server.wait_closed()
            raise
        self._queue.start()
        self._reload_lock = asyncio.Lock()
        if self.reloader is not None and self.settings.reload_interval_s is not None:
            self._poller = asyncio.get_running_loop().create_task(self._poll())
        self.ready = True
        logger.info("serving %s on %s", self.model.source.path, ", ".join(_addresses(server)))
        return server

    async def stop(self) -> None:
        """Stop polling for new models and the prediction worker (after the WebSocket server has closed)."""
        if self._poller is not None:
            self._poller.cancel()
            try:
                await self._poller
            except asyncio.CancelledError:
                pass
        await self._queue.stop()

    def close(self) -> None:
        """Release the prediction and decoding threads (after :meth:`stop`)."""
        self._executor.shutdown(wait=True)
        self._decoder.shutdown(wait=True)

    async def reload(self) -> bool:
        """Ask the reloader for the model to serve now; swap it in if it is another one.

        The new model is loaded and warmed up off the event loop while the served one goes on answering. A reloader
        that fails (registry unreachable, a checkpoint that does not load or fit its spec) is logged and the served
        model stays. Reloads run one at a time.

        Returns:
            Whether a new model was swapped in.
        """
        if self.reloader is None:
            return False
        async with self._reload_lock:
            try:
                loaded = await asyncio.to_thread(self._load_next)
            except Exception:  # noqa: BLE001 - the served model stays; the log says why the new one did not come
                logger.exception("reloading the model failed; still serving %s", self.model.source.model_version)
                return False
            if loaded is None:
                return False
            self._swap(*loaded)
            return True

    def _load_next(self) -> tuple[ServedModel, ServingSpec] | None:
        loaded = self.reloader(self.model.source)
        if loaded is not None:
            model, spec = loaded
            model.warm_up(spec)
        return loaded

    def _swap(self, model: ServedModel, spec: ServingSpec) -> None:
        """Serve `model` from the next request on (runs on the event loop, so no request sees half of it)."""
        previous = self.model.source.model_version
        spec_changed = spec != self.spec
        self.model, self.spec = model, spec
        self.metrics.reloads += 1
        logger.info("now serving %s (was %s)", model.source.model_version, previous)
        if spec_changed:
            logger.info("the spec changed; closing %d connections so that they reconnect", len(self._sessions))
            for connection in list(self._sessions):
                asyncio.get_running_loop().create_task(connection.close(SPEC_CHANGED_CLOSE_CODE, SPEC_CHANGED_REASON))

    async def _poll(self) -> None:
        while True:
            await asyncio.sleep(self.settings.reload_interval_s)
            await self.reload()

    def _count_call(self, size: int) -> None:
        self.metrics.model_calls += 1
        self.metrics.predicted_chunks += size

    def _process_request(self, connection: ServerConnection, request: Request) -> Response | None:
        path = request.path.split("?", 1)[0]
        if path == "/healthz":
            return connection.respond(http.HTTPStatus.OK, "ok\n")
        try:
            authorized = authorized_request(request.headers, self.settings.token)
        except MultipleValuesError:
            return connection.respond(http.HTTPStatus.BAD_REQUEST, "send one Authorization header, not several\n")
        if not authorized:
            response = connection.respond(http.HTTPStatus.UNAUTHORIZED, "missing or wrong bearer token\n")
            response.headers["WWW-Authenticate"] = "Bearer"
            return response
        if path == "/readyz":
            if self.ready:
                return connection.respond(http.HTTPStatus.OK, "ready\n")
            return connection.respond(http.HTTPStatus.SERVICE_UNAVAILABLE, "warming up\n")
        if path == "/metadata":
            return _with_content_type(
                connection.respond(http.HTTPStatus.OK, json.dumps(self.metadata()) + "\n"), "application/json"
            )
        if path == "/metrics":
            metrics = connection.respond(http.HTTPStatus.OK, self.metrics.render())
            return _with_content_type(metrics, METRICS_CONTENT_TYPE)
        if not self.ready:
            return connection.respond(http.HTTPStatus.SERVICE_UNAVAILABLE, "warming up\n")
        return None

    async def _handle(self, connection: ServerConnection) -> None:
        self.metrics.connections += 1
        session = Session(self.spec)
        self._sessions[connection] = session
        # websockets' own lines for each connection are at debug level (`ProbeQuietLogger`); a robot's come here.
        address = ":".join(str(part) for part in connection.remote_address[:2])
        logger.info("robot connected from %s (%d open)", address, self.metrics.connections)
        try:
            await connection.send(encode(self.metadata()))
            async for frame in connection:
                await self._answer(connection, session, frame)
        except ConnectionClosed:
            pass
        finally:
            del self._sessions[connection]
            self.metrics.connections -= 1
            logger.info("robot from %s disconnected (%d open)", address, self.metrics.connections)

    def _parse(self, frame: str | bytes) -> Any:
        if isinstance(frame, str):
            raise RequestError("frame: expected a binary msgpack frame, got text")
        if len(frame) > self.settings.max_request_bytes:
            raise RequestError(f"frame: {len(frame)} bytes exceed the limit of {self.settings.max_request_bytes}")
        try:
            return decode(frame)
        except WireError as error:
            raise RequestError(f"frame: {error}") from None

    def _observe(self, session: Session, frame: str | bytes) -> Observed:
        """Decode and validate `frame` into `session` (on a decoding thread; a connection's frames one at a time)."""
        return session.observe(self._parse(frame))

    async def _answer(self, connection: ServerConnection, session: Session, frame: str | bytes) -> None:
        received = time.perf_counter()
        # The model this request arrived under answers it, even if a reload swaps another one in meanwhile.
        model = self.model
        self.metrics.requests += 1
        try:
            observed = await asyncio.get_running_loop().run_in_executor(self._decoder, self._observe, session, frame)
        except RequestError as error:
            self.metrics.errors += 1
            await connection.send(str(error))
            if self.settings.refusal_pause_s:
                await asyncio.sleep(self.settings.refusal_pause_s)  # this connection's frames wait; no other's do
            return
        if not observed.predict:
            await connection.send(encode({**observed.echo, "model_version": model.source.model_version}))
            return
        try:
            prediction = await self._queue.predict(model, observed)
        except Exception:  # noqa: BLE001 - logged here; the client gets one line, never the traceback
            logger.exception("prediction failed")
            self.metrics.errors += 1
            await connection.send("prediction: failed on the server (see its log)")
            return
        reply = {
            "actions": prediction.actions,  # (H, A) float32
            **observed.echo,
            "model_version": model.source.model_version,
            "batch_size": prediction.batch_size,
            "timing_ms": {
                "queue": 1e3 * (prediction.started - received),
                "inference": 1e3 * (prediction.finished - prediction.started),
                "encoding": 1e3 * prediction.encoding_seconds,
            },
        }
        await connection.send(encode(reply))
        self.metrics.observe_latency(time.perf_counter() - received)


def _with_content_type(response: Response, content_type: str) -> Response:
    del response.headers["Content-Type"]
    response.headers["Content-Type"] = content_type
    return response


def _addresses(server: Server) -> list[str]:
    return [f"{socket.getsockname()[0]}:{socket.getsockname()[1]}" for socket in server.sockets]


def bound_port(server: Server) -> int:
    """The TCP port `server` listens on (the one the OS picked for port 0)."""
    return server.sockets[0].getsockname()[1]


async def _serve_until(policy_server: PolicyServer, stop: asyncio.Event, on_started) -> None:
    server = await policy_server.start()
    try:
        on_started(bound_port(server))
        await stop.wait()
    finally:
        server.close()
        await server.wait_closed()
        await policy_server.stop()
        policy_server.close()


def serve_forever(policy_server: PolicyServer) -> None:
    """Serve in this thread until interrupted (Ctrl-C or SIGTERM); SIGHUP checks for a new model at once.

    Raises:
        OSError: the address cannot be bound.
        ValueError: the warm-up prediction does not fit the spec.
    """
    import signal

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        loop.add_signal_handler(signal.SIGTERM, stop.set)
        loop.add_signal_handler(signal.SIGHUP, lambda: loop.create_task(policy_server.reload()))
        await _serve_until(policy_server, stop, lambda port: None)

    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        logger.info("interrupted; the server has stopped")


class ServerThread:
    """A `PolicyServer` running on its own event loop in a background thread (tests, embedding in a program).

    Use as a context manager: entering binds and warms up (or raises what `PolicyServer.start` raised), leaving
    closes every connection and waits for the thread.
    """

    def __init__(self, policy_server: PolicyServer) -> None:
        self.policy_server = policy_server
        self.port: int | None = None
        self._started = threading.Event()
        self._failure: BaseException | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread = threading.Thread(target=self._run, name="carp-serving-loop", daemon=True)

    @property
    def url(self) -> str:
        """``ws://host:port`` (``wss://`` with TLS) of the running server."""
        return f"{self.policy_server.scheme}://{self.policy_server.settings.host}:{self.port}"

    def _run(self) -> None:
        async def main() -> None:
            self._loop, self._stop = asyncio.get_running_loop(), asyncio.Event()

            def started(port: int) -> None:
                self.port = port
                self._started.set()

            await _serve_until(self.policy_server, self._stop, started)

        try:
            asyncio.run(main())
        except BaseException as error:  # noqa: BLE001 - handed to the thread that called `start`
            self._failure = error
        finally:
            self._started.set()

    def start(self, timeout_s: float = 60.0) -> "ServerThread":
        """Start the thread and wait until the server is ready.

        Raises:
            TimeoutError: not ready within `timeout_s`.
            OSError, ValueError: as `PolicyServer.start`.
        """
        self._thread.start()
        if not self._started.wait(timeout_s):
            raise TimeoutError(f"the server was not ready within {timeout_s} s")
        if self._failure is not None:
            raise self._failure
        return self

    def reload(self, timeout_s: float = 60.0) -> bool:
        """Run :meth:`PolicyServer.reload` on the server's loop and wait for it; returns whether it swapped."""
        return asyncio.run_coroutine_threadsafe(self.policy_server.reload(), self._loop).result(timeout_s)

    def stop(self, timeout_s: float = 30.0) -> None:
        """Close the server and its connections, and wait for the thread."""
        if self._loop is not None and self._stop is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(timeout_s)

    def __enter__(self) -> "ServerThread":
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()
