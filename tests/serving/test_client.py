import os
import socket
import subprocess
import sys

import numpy as np
import pytest
from carp_client import PolicyClient

from tests.serving.conftest import CLIENT_DIR, observations, start_server


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


def test_the_client_package_imports_neither_torch_nor_carp():
    # Compared with the modules loaded before it, so that whatever the interpreter loads at start-up does not count.
    check = (
        "import sys; before = set(sys.modules); import carp_client; "
        "new = {name.split('.')[0] for name in set(sys.modules) - before}; "
        "assert not new & {'torch', 'carp', 'onnxruntime'}, sorted(new)"
    )
    environment = os.environ | {"PYTHONPATH": str(CLIENT_DIR)}
    subprocess.run([sys.executable, "-c", check], env=environment, check=True, timeout=60)
