"""Reloading: a moved registry alias or a changed checkpoint file swaps the model between requests, none failing."""

import os
import threading

import mlflow
import numpy as np
import pytest
from carp_client import PolicyClient, SpecChangedError

from carp.data.sources import file_sha256
from carp.serving.server import PolicyServer, ServerSettings, ServerThread
from carp.serving.startup import ServingStartError, load_served_model, model_reloader
from carp.tracking.registry import register_policy_checkpoint
from tests.serving.conftest import PROTOCOL, observations, save_tiny_checkpoint

ROBOTS = 3


def serve(model, tracking_uri=None, **settings) -> ServerThread:
    served, spec = load_served_model(model, tracking_uri=tracking_uri)
    settings = ServerSettings(**({"port": 0} | settings))
    return ServerThread(PolicyServer(served, spec, settings, model_reloader(model, tracking_uri=tracking_uri))).start()


def replace_file(path, writer) -> None:
    """Write the new checkpoint beside `path`, then rename it over `path`, as a deployment would."""
    staged = path.with_name(f".{path.name}.new")
    writer(staged)
    os.replace(staged, path)


ENOUGH_REQUESTS = 2000
"""A bound on each robot's requests that it never reaches: it stops once the new model answers it."""


class Robots:
    """`ROBOTS` clients on their own threads, each sending observations until `stop_at_version` answers one."""

    def __init__(self, url: str, stop_at_version: str, requests: int = ENOUGH_REQUESTS) -> None:
        self.versions: dict[int, list[str]] = {robot: [] for robot in range(ROBOTS)}
        self.failures: list[BaseException] = []
        self.first_reply = threading.Barrier(ROBOTS + 1)
        arguments = (url, requests, stop_at_version)
        self._threads = [threading.Thread(target=self._drive, args=(robot, *arguments)) for robot in range(ROBOTS)]

    def _drive(self, robot: int, url: str, requests: int, stop_at_version: str) -> None:
        try:
            with PolicyClient(url, timeout=30) as client:
                for index, obs in enumerate(observations(requests, seed=robot)):
                    reply = client.infer({"obs": obs})
                    assert reply["actions"].shape == (8, 2) and np.isfinite(reply["actions"]).all()
                    self.versions[robot].append(reply["model_version"])
                    if index == 0:
                        self.first_reply.wait(timeout=60)
                    if reply["model_version"] == stop_at_version:
                        return
        except BaseException as error:  # noqa: BLE001 - re-raised by the test thread in `join`
            self.failures.append(error)
            self.first_reply.abort()

    def start(self) -> "Robots":
        for thread in self._threads:
            thread.start()
        self.first_reply.wait(timeout=60)  # every robot is mid-episode when the model moves
        return self

    def join(self) -> None:
        for thread in self._threads:
            thread.join(timeout=120)
        assert not self.failures, self.failures


def assert_switched_once(versions: dict[int, list[str]], old: str, new: str) -> None:
    for robot, seen in versions.items():
        assert seen[0] == old and seen[-1] == new, (robot, seen)
        switch = seen.index(new)
        assert set(seen[:switch]) == {old} and set(seen[switch:]) == {new}, (robot, seen)


def test_a_changed_checkpoint_file_is_swapped_in_between_requests_with_none_failing(tmp_path):
    path = save_tiny_checkpoint(tmp_path / "policy.pt", seed=0)
    old = file_sha256(path)[:12]
    server = serve(path)
    try:
        assert server.reload() is False  # same bytes: nothing to load
        staged = save_tiny_checkpoint(tmp_path / "staged.pt", seed=1)
        new = file_sha256(staged)[:12]
        robots = Robots(server.url, stop_at_version=new).start()
        os.replace(staged, path)
        assert server.reload() is True
        robots.join()
        with PolicyClient(server.url) as client:
            metadata = client.metadata
    finally:
        server.stop()
    assert new != old and metadata["model_version"] == new and metadata["model"]["sha256"][:12] == new
    assert_switched_once(robots.versions, old, new)
    assert server.policy_server.metrics.reloads == 1 and server.policy_server.metrics.errors == 0


def test_a_new_model_that_fails_to_load_leaves_the_served_one_in_place(tmp_path):
    path = save_tiny_checkpoint(tmp_path / "policy.pt")
    old = file_sha256(path)[:12]
    server = serve(path)
    try:
        replace_file(path, lambda staged: staged.write_bytes(b"not a checkpoint"))
        assert server.reload() is False
        with PolicyClient(server.url) as client:
            assert client.infer({"obs": observations(1, seed=0)[0]})["model_version"] == old
    finally:
        server.stop()


def test_a_changed_spec_closes_the_connections_and_the_client_says_so(tmp_path):
    path = save_tiny_checkpoint(tmp_path / "policy.pt")
    server = serve(path)
    try:
        with PolicyClient(server.url, timeout=30) as client:
            assert client.metadata["observation_keys"]["object"]["shape"] == [1]
            client.infer({"object": np.zeros(1, np.float32), "robot0_eef_pos": np.zeros(2, np.float32)})
            # The same policy, recorded as receiving `object` with two features and the end effector with one.
            replace_file(path, lambda staged: save_tiny_checkpoint(staged, serving=PROTOCOL | {"obs_widths": [2, 1]}))
            assert server.reload() is True
            with pytest.raises(SpecChangedError, match="read the metadata again"):
                client.infer({"object": np.zeros(1, np.float32), "robot0_eef_pos": np.zeros(2, np.float32)})
            assert client.metadata["observation_keys"]["object"]["shape"] == [2]
            reply = client.infer({"object": np.zeros(2, np.float32), "robot0_eef_pos": np.zeros(1, np.float32)})
            assert reply["actions"].shape == (8, 2)
    finally:
        server.stop()


def test_a_registry_uri_needs_a_tracking_uri():
    with pytest.raises(ServingStartError, match="needs the tracking URI of the registry"):
        load_served_model("models:/carp-policy-lift-carp@champion")


@pytest.mark.slow
def test_moving_the_registry_alias_switches_versions_with_zero_failed_requests(tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    first = save_tiny_checkpoint(tmp_path / "v1" / "policy.pt", seed=0)
    second = save_tiny_checkpoint(tmp_path / "v2" / "policy.pt", seed=1)
    champion = register_policy_checkpoint(uri, first, "champion")
    candidate = register_policy_checkpoint(uri, second, "candidate")
    assert (champion.name, champion.version, candidate.version) == ("carp-policy-lift-carp", "1", "2")
    assert register_policy_checkpoint(uri, first, "champion").version == "1"  # same bytes: the same version

    model_uri = "models:/carp-policy-lift-carp@champion"
    with pytest.raises(ServingStartError, match="carp-policy-lift-carp@nobody: not found in the registry"):
        load_served_model("models:/carp-policy-lift-carp@nobody", tracking_uri=uri)
    server = serve(model_uri, tracking_uri=uri, reload_interval_s=0.05)
    try:
        with PolicyClient(server.url) as client:
            metadata = client.metadata
        assert metadata["model_version"] == "1"
        assert metadata["model"] == {
            "path": model_uri, "sha256": file_sha256(first), "name": champion.name, "version": "1", "alias": "champion"
        }  # fmt: skip
        robots = Robots(server.url, stop_at_version="2").start()
        mlflow.MlflowClient(tracking_uri=uri).set_registered_model_alias(champion.name, "champion", "2")
        robots.join()
        with PolicyClient(server.url) as client:
            metadata = client.metadata
    finally:
        server.stop()
    assert_switched_once(robots.versions, "1", "2")
    assert metadata["model"]["sha256"] == file_sha256(second) and metadata["model"]["version"] == "2"
    assert server.policy_server.metrics.errors == 0
