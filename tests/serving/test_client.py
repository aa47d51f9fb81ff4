import base64
import hashlib
import inspect
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
from carp_client import PolicyClient

from tests.serving.conftest import CLIENT_DIR, observations, start_server
from tests.serving.openpi_style_client import OpenpiStyleClient

PROJECT_DIR = Path(__file__).resolve().parents[2]
WEBSOCKET_GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
"""RFC 6455's constant of the opening handshake's accept key."""


class SilentServer:
    """Accepts one connection, completes the WebSocket handshake and sends a metadata frame, then reads nothing and
    answers nothing, not even a close frame: a server hung after it accepted the robot."""

    def __init__(self) -> None:
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.url = f"ws://127.0.0.1:{self._listener.getsockname()[1]}"
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        connection, _ = self._listener.accept()
        with connection:
            request = b""
            while b"\r\n\r\n" not in request:
                request += connection.recv(4096)
            key = next(
                line.split(b":", 1)[1].strip()
                for line in request.split(b"\r\n")
                if line.lower().startswith(b"sec-websocket-key:")
            )
            accept = base64.b64encode(hashlib.sha1(key + WEBSOCKET_GUID).digest())
            connection.sendall(
                b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                b"Sec-WebSocket-Accept: " + accept + b"\r\n\r\n"
            )
            metadata = msgpack.packb({"protocol": "carp-policy"})
            connection.sendall(bytes([0x82, len(metadata)]) + metadata)  # one unmasked binary frame
            self._done.wait(60)

    def close(self) -> None:
        self._done.set()
        self._thread.join(10)
        self._listener.close()


def test_a_reply_that_never_comes_raises_within_the_timeout_not_twice_it():
    hung = SilentServer()
    try:
        client = PolicyClient(hung.url, timeout=1.5, connect_attempts=1)
        client.connect()
        started = time.monotonic()
        with pytest.raises(TimeoutError, match="no reply .* within 1.5 s"):
            client.infer({"obs": np.zeros(3, np.float32)})
        elapsed = time.monotonic() - started
    finally:
        hung.close()
    # Waiting for a closing handshake the hung server never answers would take another 1.5 s.
    assert elapsed < 1.5 * 1.5, elapsed


def test_connecting_to_a_server_that_accepts_and_never_answers_gives_up_within_the_budget():
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        url = f"ws://127.0.0.1:{listener.getsockname()[1]}"
        started = time.monotonic()
        with pytest.raises(TimeoutError, match="within 2 s"):
            PolicyClient(url, timeout=0.5, reconnect_budget_s=2.0).connect()
        elapsed = time.monotonic() - started
    assert elapsed < 2.0 + 0.5, elapsed


def test_the_client_times_out_against_a_server_that_never_answers():
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        url = f"ws://127.0.0.1:{listener.getsockname()[1]}"
        with pytest.raises(TimeoutError, match="2 attempts"):
            PolicyClient(url, timeout=0.3, connect_attempts=2, initial_backoff_s=0.05).connect()


def test_the_client_gives_up_after_its_attempts_when_nothing_listens():
    with socket.socket() as unused:
        unused.bind(("127.0.0.1", 0))
        port = unused.getsockname()[1]
    with pytest.raises(ConnectionError, match="3 attempts"):
        PolicyClient(f"ws://127.0.0.1:{port}", timeout=1, connect_attempts=3, initial_backoff_s=0.01).connect()


def test_the_client_reconnects_to_a_server_restarted_on_the_same_port(checkpoint):
    first = start_server(checkpoint)
    port = first.port
    with PolicyClient(first.url, timeout=10, connect_attempts=20, initial_backoff_s=0.05, max_backoff_s=0.5) as client:
        obs = observations(1, seed=0)[0]
        assert client.infer({"obs": obs})["actions"].shape == (8, 2)
        first.stop()
        second = start_server(checkpoint, port=port)
        try:
            reply = client.infer({"obs": obs})
        finally:
            second.stop()
    assert reply["actions"].shape == (8, 2) and reply["actions"].dtype == np.float32


TOKEN = "s3cret-token"


def serve_in_a_process(checkpoint, port: int) -> subprocess.Popen:
    """`carp serve` of `checkpoint` on `port`, its token in the environment (where a deployment keeps it)."""
    environment = os.environ | {"PYTHONPATH": str(PROJECT_DIR / "src"), "CARP_SERVE_TOKEN": TOKEN}
    command = [sys.executable, "-m", "carp.cli", "serve", "--model", str(checkpoint), "--port", str(port)]
    return subprocess.Popen(
        [*command, "--reload-interval", "0"], cwd=PROJECT_DIR, env=environment, stderr=subprocess.DEVNULL
    )


@pytest.mark.slow
def test_the_client_waits_for_a_server_killed_and_restarted(checkpoint):
    with socket.socket() as unused:
        unused.bind(("127.0.0.1", 0))
        port = unused.getsockname()[1]
    assert inspect.signature(PolicyClient).parameters["reconnect_budget_s"].default == 30.0
    process = serve_in_a_process(checkpoint, port)
    try:
        # The client waits for the first start too: the process imports torch, loads and exports the policy. A start
        # takes 5-11 s on an idle 2-core machine, within the default budget; a machine running the test suite beside
        # other jobs can take several times that, so the budget here is wider than the default.
        with PolicyClient(f"ws://127.0.0.1:{port}", token=TOKEN, reconnect_budget_s=180.0) as client:
            obs = observations(1, seed=0)[0]
            assert client.infer({"obs": obs})["actions"].shape == (8, 2)
            process.send_signal(signal.SIGKILL)
            process.wait(30)
            process = serve_in_a_process(checkpoint, port)
            reply = client.infer({"obs": obs})
        # A client written as openpi's is, with its Api-Key scheme and numpy scalars, against `carp serve` itself.
        openpi = OpenpiStyleClient(f"ws://127.0.0.1:{port}", api_key=TOKEN)
        try:
            openpi_reply = openpi.infer({"obs": obs, "step": np.int64(0), "prompt": "lift the cube"})
        finally:
            openpi.close()
    finally:
        process.kill()
        process.wait(30)
    assert reply["actions"].shape == (8, 2) and reply["actions"].dtype == np.float32
    assert openpi_reply["step"] == 0 and openpi_reply["actions"].shape == (8, 2)


def test_the_client_package_imports_neither_torch_nor_carp():
    # Compared with the modules loaded before it, so that whatever the interpreter loads at start-up does not count.
    check = (
        "import sys; before = set(sys.modules); import carp_client; "
        "new = {name.split('.')[0] for name in set(sys.modules) - before}; "
        "assert not new & {'torch', 'carp', 'onnxruntime'}, sorted(new)"
    )
    environment = os.environ | {"PYTHONPATH": str(CLIENT_DIR)}
    subprocess.run([sys.executable, "-c", check], env=environment, check=True, timeout=60)
