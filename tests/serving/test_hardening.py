"""A server that misbehaving clients cannot stall, its authentication and TLS, and openpi's own client against it."""

import datetime
import http.client
import logging
import signal
import ssl
import subprocess
import sys
import time
import urllib.request

import msgpack
import numpy as np
import pytest
import torch
from carp_client import PolicyClient
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from carp.serving.access import is_loopback
from carp.serving.model import ServedModel
from carp.serving.server import PolicyServer, ServerSettings, ServerThread
from tests.serving.conftest import SPEC, observations, served_model, start_server
from tests.serving.openpi_style_client import OpenpiStyleClient

GOOD = np.zeros(3, np.float32)
INFERENCE_SECONDS = 0.02
"""What the stand-in policy's prediction takes: a real policy's order of magnitude, so that a p99 is not noise."""


class SlowPolicy:
    """The tiny policy, each prediction taking `INFERENCE_SECONDS` more (in a sleep, which holds no lock)."""

    def __init__(self, policy) -> None:
        self._policy = policy

    def __getattr__(self, name: str):
        return getattr(self._policy, name)

    def predict_action_timed(self, *args, **kwargs):
        time.sleep(INFERENCE_SECONDS)
        return self._policy.predict_action_timed(*args, **kwargs)


def round_trip_seconds(url: str, requests: int) -> list[float]:
    seconds = []
    with PolicyClient(url, timeout=30) as client:
        for obs in observations(requests, seed=3):
            started = time.perf_counter()
            client.infer({"obs": obs})
            seconds.append(time.perf_counter() - started)
    return seconds


ATTACKER = """
import sys
import msgpack
from websockets.sync.client import connect

# A frame of a million empty maps, each one byte: just under the server's default 1 MiB limit.
frame = msgpack.packb([{}] * ((1 << 20) - 16))
with connect(sys.argv[1], compression=None, open_timeout=30, max_size=None) as connection:
    connection.recv(timeout=30)  # metadata
    print("attacking", flush=True)
    while True:
        connection.send(frame)
        reply = connection.recv(timeout=60)
        if not isinstance(reply, str):
            raise SystemExit(f"a reply that is not an error line: {reply!r}")
        print("refused", flush=True)
"""


@pytest.mark.slow
def test_a_client_sending_worst_case_frames_leaves_another_clients_p99_within_twice_its_quiet_one(checkpoint):
    model = served_model(checkpoint)
    slow = ServedModel(SlowPolicy(model.policy), model.source, model.inference)
    settings = ServerSettings(port=0)  # the default frame limit, 1 MiB
    quiet, loaded = [], []
    with ServerThread(PolicyServer(slow, SPEC, settings)) as server:
        # Another process, as an attacker would be: its own sending costs this process nothing.
        attacker = subprocess.Popen(
            [sys.executable, "-c", ATTACKER, server.url], stdout=subprocess.PIPE, text=True, bufsize=1
        )
        try:
            assert attacker.stdout.readline().strip() == "attacking"
            assert attacker.stdout.readline().strip() == "refused"  # its frames are on their way
            # Quiet and attacked blocks alternate (the attacker stopped and continued), so that the other jobs of a
            # shared machine weigh on both alike; short blocks (about half a second) keep a burst of those jobs from
            # landing on one side only.
            for _ in range(10):
                attacker.send_signal(signal.SIGSTOP)
                quiet += round_trip_seconds(server.url, 20)
                attacker.send_signal(signal.SIGCONT)
                loaded += round_trip_seconds(server.url, 20)
            assert attacker.poll() is None, "the attacker stopped"
        finally:
            attacker.kill()
            refused = attacker.stdout.read().split().count("refused") + 1
            attacker.wait(30)
    quiet_p99, loaded_p99 = np.percentile(quiet, 99), np.percentile(loaded, 99)
    assert loaded_p99 <= 2 * quiet_p99, (quiet_p99, loaded_p99, refused)
    assert refused >= 10, "the attacker sent too few frames to load the server"


def raw_get(port: int, path: str, headers: list[tuple[str, str]], context: ssl.SSLContext | None = None):
    """(status, body) of a GET with `headers` as given, repeated names included (urllib would merge them)."""
    if context is None:
        connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    else:
        connection = http.client.HTTPSConnection("127.0.0.1", port, timeout=10, context=context)
    connection.putrequest("GET", path)
    for name, value in headers:
        connection.putheader(name, value)
    connection.endheaders()
    response = connection.getresponse()
    status, body = response.status, response.read().decode()
    connection.close()
    return status, body


@pytest.fixture(scope="module")
def guarded(checkpoint):
    # Built on one torch thread, as the package's `server` fixture is, so that its chunks match the references.
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        running = start_server(checkpoint, token="s3cret")
    finally:
        torch.set_num_threads(previous)
    yield running
    running.stop()


@pytest.mark.parametrize(
    "value, status",
    [
        ("Bearer s3cret", 200),
        ("bearer s3cret", 200),
        ("BEARER s3cret", 200),
        ("Api-Key s3cret", 200),
        ("api-key s3cret", 200),
        ("Basic s3cret", 401),
        ("Bearer wrong", 401),
        ("s3cret", 401),
    ],
)
def test_authorization_schemes_are_case_insensitive_and_openpis_api_key_is_accepted(guarded, value, status):
    assert raw_get(guarded.port, "/readyz", [("Authorization", value)])[0] == status


def test_two_authorization_headers_get_400_and_leave_no_traceback(guarded, caplog):
    with caplog.at_level(logging.DEBUG):
        status, body = raw_get(
            guarded.port, "/metadata", [("Authorization", "Bearer s3cret"), ("Authorization", "Bearer s3cret")]
        )
    assert status == 400 and "one Authorization header" in body
    assert not [record for record in caplog.records if record.exc_info or record.levelno >= logging.ERROR]


def test_health_probes_are_logged_at_debug_level_only(server, caplog):
    with caplog.at_level(logging.DEBUG, logger="websockets"):
        for path in ("/healthz", "/readyz", "/healthz"):
            with urllib.request.urlopen(f"http://127.0.0.1:{server.port}{path}", timeout=10) as response:
                assert response.status == 200
        records = [record for record in caplog.records if record.name.startswith("websockets")]
    lines = [(record.levelno, record.getMessage()) for record in records]
    assert any("(200 OK)" in message for _, message in lines), lines
    assert all(level == logging.DEBUG for level, _ in lines), lines


def test_a_non_loopback_address_needs_a_token_or_an_explicit_choice():
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("robot-server.local")
    with pytest.raises(ValueError, match="reachable from other machines: set a token"):
        ServerSettings(host="0.0.0.0")
    assert ServerSettings(host="0.0.0.0", token="s3cret").token == "s3cret"
    assert ServerSettings(host="0.0.0.0", allow_no_token=True).token is None


def self_signed_pair(folder) -> tuple[str, str]:
    """A certificate for 127.0.0.1 and localhost that signs itself, and its key, as PEM files in `folder`."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "carp test server")])
    now = datetime.datetime.now(datetime.UTC)
    alternative_names = x509.SubjectAlternativeName(
        [x509.DNSName("localhost"), x509.IPAddress(__import__("ipaddress").ip_address("127.0.0.1"))]
    )
    certificate = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(alternative_names, critical=False)
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    certificate_file, key_file = folder / "server.pem", folder / "server.key"
    certificate_file.write_bytes(certificate.public_bytes(serialization.Encoding.PEM))
    key_file.write_bytes(
        key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )
    return str(certificate_file), str(key_file)


def test_tls_with_a_self_signed_certificate_serves_wss_and_https(checkpoint, tmp_path):
    certificate, key = self_signed_pair(tmp_path)
    trusting = ssl.create_default_context(cafile=certificate)
    running = start_server(checkpoint, token="s3cret", tls_certificate=certificate, tls_key=key)
    try:
        assert running.url.startswith("wss://127.0.0.1:")
        assert raw_get(running.port, "/readyz", [("Authorization", "Bearer s3cret")], trusting) == (200, "ready\n")
        with PolicyClient(running.url, token="s3cret", timeout=10, ssl_context=trusting) as client:
            assert client.infer({"obs": GOOD})["actions"].shape == (8, 2)
        # A client that does not trust the certificate, or speaks plain HTTP, gets nothing.
        with pytest.raises(ssl.SSLCertVerificationError):
            raw_get(running.port, "/readyz", [], ssl.create_default_context())
        with pytest.raises((ConnectionError, http.client.HTTPException, OSError)):
            raw_get(running.port, "/healthz", [])
    finally:
        running.stop()


def test_a_tls_key_that_does_not_match_its_certificate_is_refused_in_one_line(tmp_path):
    from carp.serving.access import tls_context

    certificate, _ = self_signed_pair(tmp_path)
    other = tmp_path / "other"
    other.mkdir()
    _, other_key = self_signed_pair(other)
    with pytest.raises(ValueError, match="tls: .*server.pem: not a PEM certificate and key that match"):
        tls_context(certificate, other_key)
    with pytest.raises(ValueError, match="tls: .*missing.pem: no such file"):
        tls_context(str(tmp_path / "missing.pem"))


def test_an_openpi_style_client_with_its_api_key_and_numpy_scalars_gets_the_served_chunks(guarded, reference_policy):
    from tests.serving.conftest import in_process_chunks

    episode = observations(4, seed=21)
    client = OpenpiStyleClient(guarded.url, api_key="s3cret")
    try:
        assert client.metadata["protocol"] == "carp-policy"
        replies = []
        for step, obs in enumerate(episode):
            request = {"obs": obs, "step": np.int64(step), "timestamp": np.float64(step * 0.05), "prompt": "lift"}
            if step == 0:
                request.update(reset=np.bool_(True), seed=np.int64(6))
            replies.append(client.infer(request))
        with pytest.raises(RuntimeError, match=r"obs: expected shape \(3,\), got \(2,\)"):
            client.infer({"obs": np.zeros(2, np.float32)})
    finally:
        client.close()
    assert [reply["step"] for reply in replies] == list(range(4))
    for reply, chunk in zip(replies, in_process_chunks(reference_policy, episode, seed=6), strict=True):
        np.testing.assert_array_equal(reply["actions"], chunk)
    with pytest.raises(InvalidStatus) as refused:
        OpenpiStyleClient(guarded.url, api_key="wrong")
    assert refused.value.response.status_code == 401


def test_a_request_with_a_timestamp_extension_gets_one_error_line(server):
    with connect(server.url, compression=None, open_timeout=10) as connection:
        connection.recv(timeout=10)
        connection.send(msgpack.packb({"obs": None, "timestamp": msgpack.Timestamp(5, 0)}, datetime=False))
        assert connection.recv(timeout=10) == "frame: msgpack extension type -1 is not accepted"
