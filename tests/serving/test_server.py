import json
import threading
import urllib.error
import urllib.request

import msgpack
import numpy as np
import pytest
import torch
from carp_client import PolicyClient, ServerError
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from carp.serving.settings import DEFAULT_HOST, ServerSettings
from carp.serving.wire import decode, encode
from tests.serving.conftest import (
    MAX_REQUEST_BYTES,
    SPEC,
    in_process_chunks,
    observations,
    start_server,
)


def http_get(server, path: str, token: str | None = None) -> tuple[int, str, str]:
    request = urllib.request.Request(f"http://127.0.0.1:{server.port}{path}")
    if token is not None:
        request.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            return response.status, response.headers["Content-Type"], response.read().decode()
    except urllib.error.HTTPError as error:
        return error.code, error.headers["Content-Type"], error.read().decode()


def metric(server, name: str) -> float:
    _, _, text = http_get(server, "/metrics")
    return float(next(line.split()[-1] for line in text.splitlines() if line.startswith(name + " ")))


def test_served_chunks_equal_in_process_prediction_bit_for_bit(server, reference_policy):
    first, second = observations(6, seed=1), observations(4, seed=2)
    with PolicyClient(server.url, timeout=10) as client:
        client.reset(seed=3)
        served = [client.infer({"obs": obs}) for obs in first]
        client.reset(seed=4)  # a new episode on the same connection: padded again, reseeded
        served += [client.infer({"obs": obs}) for obs in second]
    expected = in_process_chunks(reference_policy, first, 3) + in_process_chunks(reference_policy, second, 4)
    for step, (reply, chunk) in enumerate(zip(served, expected, strict=True)):
        assert reply["actions"].dtype == np.float32 and reply["actions"].shape == (8, 2)
        np.testing.assert_array_equal(reply["actions"], chunk)
        assert reply["step"] == step
        assert set(reply["timing_ms"]) == {"queue", "inference", "encoding"}
    # The sampling matters here: another seed gives other chunks, so the comparison above checks the seeding.
    assert any(not np.array_equal(a, b) for a, b in zip(expected[:6], in_process_chunks(reference_policy, first, 5)))


def test_per_key_requests_get_the_chunks_of_the_concatenated_obs(server, reference_policy):
    episode = observations(3, seed=7)
    with PolicyClient(server.url, timeout=10) as client:
        client.reset(seed=2)
        served = [client.infer({"object": obs[:1], "robot0_eef_pos": obs[1:]})["actions"] for obs in episode]
    for reply, chunk in zip(served, in_process_chunks(reference_policy, episode, 2), strict=True):
        np.testing.assert_array_equal(reply, chunk)


def test_observation_only_requests_fill_the_history_without_drawing_a_prediction(server, reference_policy):
    episode = observations(5, seed=9)
    with PolicyClient(server.url, timeout=10) as client:
        client.reset(seed=1)
        first = client.infer({"obs": episode[0]})["actions"]
        replies = [client.observe({"obs": obs}) for obs in episode[1:4]]
        last = client.infer({"obs": episode[4]})["actions"]
    assert [reply["step"] for reply in replies] == [1, 2, 3] and all("actions" not in reply for reply in replies)
    # Two predictions, two draws: the second sees steps 3 and 4, as a rollout executing Ta = 4 actions would.
    generator = torch.Generator().manual_seed(1)
    for history, served in (([episode[0]] * 2, first), (episode[3:5], last)):
        expected = reference_policy.predict_action_timed(np.stack(history)[None], generator=generator).actions[0]
        np.testing.assert_array_equal(served, expected)


def test_the_metadata_frame_and_route_describe_the_policy_and_its_spec(server, checkpoint):
    with PolicyClient(server.url) as client:
        metadata = client.metadata
    status, content_type, body = http_get(server, "/metadata")
    assert status == 200 and content_type == "application/json"
    assert json.loads(body) == metadata
    assert metadata["protocol"] == "carp-policy" and metadata["protocol_version"] == 1
    assert metadata["model"]["path"] == str(checkpoint) and len(metadata["model"]["sha256"]) == 64
    assert metadata["model"]["name"] is None
    assert metadata["policy_type"] == "carp" and metadata["inference"] == {"top_k": 8}
    assert metadata["observation"]["obs"] == {
        "shape": [3], "dtype": "float32", "keys": ["object", "robot0_eef_pos"], "widths": [1, 2]
    }  # fmt: skip
    assert metadata["observation_keys"] == {
        "object": {"shape": [1], "dtype": "float32"}, "robot0_eef_pos": {"shape": [2], "dtype": "float32"}
    }  # fmt: skip
    assert metadata["action"] == {"shape": [8, 2], "dtype": "float32"}
    assert (metadata["obs_steps"], metadata["executed_offset"], metadata["action_steps"]) == (2, 1, 4)
    assert metadata["control_period_s"] == SPEC.control_period_s


def test_health_readiness_and_metrics_routes(server):
    assert http_get(server, "/healthz")[0] == 200
    assert http_get(server, "/readyz")[0] == 200
    status, content_type, _ = http_get(server, "/metrics")
    assert status == 200 and content_type.startswith("text/plain; version=0.0.4")
    requests, errors = metric(server, "carp_serving_requests_total"), metric(server, "carp_serving_errors_total")
    answered = metric(server, "carp_serving_request_seconds_count")
    with PolicyClient(server.url) as client:
        for obs in observations(5, seed=7):
            client.infer({"obs": obs})
    assert metric(server, "carp_serving_requests_total") == requests + 5
    assert metric(server, "carp_serving_errors_total") == errors
    assert metric(server, "carp_serving_request_seconds_count") == answered + 5


GOOD = np.zeros(3, np.float32)
BAD_REQUESTS = [
    (encode({"step": 1}), "obs"),
    (encode({"obs": np.zeros(4, np.float32)}), "obs"),
    (encode({"obs": np.zeros(3, np.float64)}), "obs"),
    (encode({"obs": np.array([0, np.nan, 0], np.float32)}), "obs"),
    (encode({"obs": GOOD, "reset": "yes"}), "reset"),
    (encode({"obs": GOOD, "padding": b"x" * (MAX_REQUEST_BYTES + 1)}), "frame"),
    (b"\xc1\x00", "frame"),
    ("a text frame", "frame"),
]


@pytest.mark.parametrize(
    "frame, key", BAD_REQUESTS, ids=[f"{key}-{index}" for index, (_, key) in enumerate(BAD_REQUESTS)]
)
def test_a_bad_request_gets_one_error_line_naming_its_key_and_the_connection_stays_usable(server, frame, key):
    errors = metric(server, "carp_serving_errors_total")
    with connect(server.url, compression=None, open_timeout=10) as connection:
        connection.recv(timeout=10)  # metadata
        connection.send(frame)
        error = connection.recv(timeout=10)
        assert isinstance(error, str)
        assert error.startswith(f"{key}: ") and "\n" not in error and "Traceback" not in error
        connection.send(encode({"obs": GOOD, "step": 9}))
        reply = decode(connection.recv(timeout=10))
    assert reply["actions"].shape == (8, 2) and reply["step"] == 9
    assert metric(server, "carp_serving_errors_total") == errors + 1


def test_the_client_raises_the_servers_error_line_and_goes_on(server):
    with PolicyClient(server.url) as client:
        with pytest.raises(ServerError, match=r"obs: expected shape \(3,\), got \(2,\)"):
            client.infer({"obs": np.zeros(2, np.float32)})
        assert client.infer({"obs": GOOD})["actions"].shape == (8, 2)


def test_robots_on_separate_connections_do_not_share_histories(server, reference_policy):
    episodes = {robot: observations(20, seed=100 + robot) for robot in range(4)}
    served: dict[int, list[np.ndarray]] = {}
    failures: list[BaseException] = []

    def drive(robot: int) -> None:
        try:
            with PolicyClient(server.url, timeout=30) as client:
                client.reset(seed=robot)
                served[robot] = [client.infer({"obs": obs})["actions"] for obs in episodes[robot]]
        except BaseException as error:  # noqa: BLE001 - re-raised by the test thread below
            failures.append(error)

    threads = [threading.Thread(target=drive, args=(robot,)) for robot in episodes]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    assert not failures, failures
    for robot, episode in episodes.items():
        for chunk, expected in zip(served[robot], in_process_chunks(reference_policy, episode, robot), strict=True):
            np.testing.assert_array_equal(chunk, expected)


def test_an_openpi_style_client_gets_valid_replies(server):
    """Plain websockets and msgpack, arrays as maps with binary keys, as openpi's `msgpack_numpy` writes them."""

    def as_array(tagged):
        if b"__ndarray__" in tagged:
            return np.ndarray(buffer=tagged[b"data"], dtype=np.dtype(tagged[b"dtype"]), shape=tagged[b"shape"])
        return tagged

    obs = np.arange(3, dtype=np.float32)
    packed = {b"__ndarray__": True, b"data": obs.tobytes(), b"dtype": obs.dtype.str, b"shape": obs.shape}
    with connect(server.url, open_timeout=10) as connection:
        metadata = msgpack.unpackb(connection.recv(timeout=10), object_hook=as_array)
        connection.send(msgpack.packb({"obs": packed, "prompt": "ignored"}))
        reply = msgpack.unpackb(connection.recv(timeout=10), object_hook=as_array)
    assert metadata["protocol"] == "carp-policy"
    assert reply["actions"].shape == (8, 2) and reply["actions"].dtype == np.float32


def test_the_default_bind_is_loopback_and_a_token_guards_everything_but_healthz(checkpoint):
    assert ServerSettings().host == DEFAULT_HOST == "127.0.0.1"
    guarded = start_server(checkpoint, token="s3cret")
    try:
        assert guarded.policy_server.settings.host == "127.0.0.1"
        assert http_get(guarded, "/healthz")[0] == 200
        assert http_get(guarded, "/metadata")[0] == 401
        assert http_get(guarded, "/metadata", token="wrong")[0] == 401
        assert http_get(guarded, "/metadata", token="s3cret")[0] == 200
        for headers in (None, {"Authorization": "Bearer wrong"}):
            with pytest.raises(InvalidStatus) as refused:
                connect(guarded.url, additional_headers=headers, open_timeout=10)
            assert refused.value.response.status_code == 401
        with pytest.raises(PermissionError, match="HTTP 401"):
            PolicyClient(guarded.url, token="wrong").connect()
        with PolicyClient(guarded.url, token="s3cret") as client:
            assert client.infer({"obs": GOOD})["actions"].shape == (8, 2)
    finally:
        guarded.stop()
