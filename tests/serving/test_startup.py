import threading

import numpy as np
import pytest
import torch
from carp_client import PolicyClient

from carp import cli
from carp.config import DataConfig, Params
from carp.policies.base import Deployment
from carp.policies.carp.config import CarpInference
from carp.policies.carp.onnx_policy import OnnxPolicy
from carp.policies.registry import load_policy
from carp.serving.protocol import SERVING_METADATA_KEY
from carp.serving.server import PolicyServer, ServerSettings, ServerThread
from carp.serving.session import Observed
from carp.serving.startup import ServingStartError, _deployed, load_served_model
from tests.policies.carp.factories import OBS_STEPS, tiny_policy
from tests.serving.conftest import PROTOCOL, SPEC, in_process_chunks, observations, save_tiny_checkpoint


def test_a_checkpoint_that_records_its_protocol_is_served_without_params(checkpoint):
    model, spec = load_served_model(checkpoint)
    assert spec == SPEC
    assert model.inference == {"top_k": 1}  # the CARP family's default: greedy


def test_params_choose_the_inference_settings_but_not_the_recorded_spec(checkpoint):
    params = Params(data=DataConfig(obs_steps=1), inference={"carp": CarpInference(top_k=3)})
    model, spec = load_served_model(checkpoint, params)
    assert spec == SPEC and model.inference == {"top_k": 3} and model.policy.top_k == 3


def test_a_recorded_control_rate_serves_a_task_the_registry_does_not_know(tmp_path):
    # A task without a simulator is known only from its dataset: its checkpoint records the rate it is paced at.
    offline = save_tiny_checkpoint(
        tmp_path / "offline.pt", task="my_robot", serving=PROTOCOL | {"control_frequency_hz": 10}
    )
    _, spec = load_served_model(offline)
    assert spec.control_period_s == pytest.approx(0.1) and spec.obs_keys == SPEC.obs_keys


def test_a_checkpoint_without_the_protocol_needs_the_params_it_was_trained_with(tmp_path):
    old = save_tiny_checkpoint(tmp_path / "old.pt", serving=None)
    with pytest.raises(ServingStartError, match="does not record its serving protocol.*pass --params"):
        load_served_model(old)
    _, spec = load_served_model(old, Params(data=DataConfig(obs_keys=("object", "robot0_eef_pos"))))
    assert spec.obs_keys == SPEC.obs_keys and spec.obs_widths is None  # requests must send the concatenated obs
    assert (spec.obs_steps, spec.action_horizon, spec.action_steps) == (2, 16, 8)


def test_a_recorded_protocol_that_does_not_fit_the_policy_is_refused(tmp_path):
    wrong = save_tiny_checkpoint(tmp_path / "wrong.pt", serving=PROTOCOL | {"obs_widths": [1, 3]})
    with pytest.raises(ServingStartError, match=r"obs_widths \[1, 3\] of keys \['object', 'robot0_eef_pos'\] do not"):
        load_served_model(wrong)
    future = save_tiny_checkpoint(tmp_path / "future.pt", serving=PROTOCOL | {"format": 2})
    with pytest.raises(ServingStartError, match="serving protocol format 2, this carp reads 1"):
        load_served_model(future)


def test_serve_without_params_for_an_old_checkpoint_prints_one_error_line(tmp_path, capsys):
    old = save_tiny_checkpoint(tmp_path / "old.pt", serving=None)
    with pytest.raises(SystemExit) as exited:
        cli.main(["serve", "--model", str(old)])
    assert exited.value.code == 1
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {old}: the checkpoint does not record its serving protocol")


def test_the_onnxruntime_backend_serves_carps_exported_graphs_one_request_per_call(checkpoint):
    in_torch, _ = load_served_model(checkpoint)
    in_onnx, spec = load_served_model(checkpoint, backend="onnxruntime")
    assert spec == SPEC and isinstance(in_onnx.policy, OnnxPolicy) and in_onnx.backend == "onnxruntime"
    assert in_torch.backend == "torch" and in_torch.batches and not in_onnx.batches
    for seed in range(3):
        history = np.stack(observations(OBS_STEPS, seed))  # (To, Do)
        chunks = [model.predict(Observed(history, None, torch.Generator()))[0].actions for model in (in_torch, in_onnx)]
        assert chunks[1].shape == (1, SPEC.action_horizon, SPEC.action_dim)
        np.testing.assert_allclose(chunks[1], chunks[0], rtol=1e-5, atol=1e-5)


def test_carp_serve_runs_carps_graphs_unless_told_torch(checkpoint, monkeypatch):
    from carp.serving import startup

    served = []
    monkeypatch.setattr(startup, "serve_forever", lambda server: served.append(server.model))
    cli.main(["serve", "--model", str(checkpoint)])
    cli.main(["serve", "--model", str(checkpoint), "--backend", "torch"])
    assert [model.backend for model in served] == ["onnxruntime", "torch"]
    assert isinstance(served[0].policy, OnnxPolicy) and served[1].batches


def test_a_multi_task_policy_serves_the_task_named_at_startup(tmp_path):
    policy = tiny_policy(seed=3, num_tasks=2, task_names=("lift", "can"))
    policy.metadata[SERVING_METADATA_KEY] = PROTOCOL
    path = tmp_path / "multitask.pt"
    policy.save(path)
    with pytest.raises(ServingStartError, match=r"multi-task policy over \['lift', 'can'\]; name the task"):
        load_served_model(path)
    with pytest.raises(ServingStartError, match=r"trained on tasks \['lift', 'can'\], not on 'square'"):
        load_served_model(path, task="square")
    history = np.stack(observations(OBS_STEPS, seed=0))
    chunks = {}
    for task in ("lift", "can"):
        served, spec = load_served_model(path, task=task)
        assert spec == SPEC and served.task == task and served.policy.tasks.selected == task
        chunks[task] = served.predict(Observed(history, None, torch.Generator()))[0].actions
        reference = load_policy(path)
        reference.select_task(task)
        np.testing.assert_array_equal(chunks[task], reference.predict_action_timed(history[None]).actions)
        in_onnx, _ = load_served_model(path, backend="onnxruntime", task=task)
        assert in_onnx.backend == "onnxruntime" and in_onnx.task == task
        np.testing.assert_allclose(
            in_onnx.predict(Observed(history, None, torch.Generator()))[0].actions, chunks[task], atol=1e-5
        )
    # Each task's own statistics and id: the chunks differ.
    assert np.abs(chunks["lift"] - chunks["can"]).max() > 1e-3


def test_a_padded_multi_task_policy_serves_each_task_with_its_own_key_widths(tmp_path):
    widths = {"lift": (1, 1), "can": (1, 2)}  # Can's is the padded layout, Lift's eef key one feature narrower
    policy = tiny_policy(seed=3, num_tasks=2, task_names=("lift", "can"), obs_widths=widths)
    policy.metadata[SERVING_METADATA_KEY] = PROTOCOL
    path = tmp_path / "padded.pt"
    policy.save(path)
    assert load_served_model(path, task="can")[1] == SPEC
    served, spec = load_served_model(path, task="lift")
    assert (spec.obs_widths, spec.obs_dim) == ((1, 1), 2)
    history = np.stack(observations(OBS_STEPS, seed=0))[:, :2]  # Lift's own (To, 2)
    chunk = served.predict(Observed(history, None, torch.Generator()))[0].actions
    reference = load_policy(path)
    reference.select_task("lift")
    np.testing.assert_array_equal(chunk, reference.predict_action_timed(history[None]).actions)
    in_onnx, _ = load_served_model(path, backend="onnxruntime", task="lift")
    np.testing.assert_allclose(in_onnx.predict(Observed(history, None, torch.Generator()))[0].actions, chunk, atol=1e-5)


def test_a_single_task_policy_refuses_another_task(checkpoint):
    assert load_served_model(checkpoint, task="lift")[0].task == "lift"
    with pytest.raises(ServingStartError, match="task 'can': this policy was trained on 'lift' only"):
        load_served_model(checkpoint, task="can")


def test_a_server_on_the_onnxruntime_backend_names_it_and_matches_its_graphs_in_process(checkpoint):
    model, spec = load_served_model(checkpoint, backend="onnxruntime")
    episode = observations(5, seed=11)
    running = ServerThread(PolicyServer(model, spec, ServerSettings(port=0))).start()
    try:
        with PolicyClient(running.url, timeout=10) as client:
            assert client.metadata["backend"] == "onnxruntime"
            client.reset(seed=0)
            served = [client.infer({"obs": obs})["actions"] for obs in episode]
    finally:
        running.stop()
    for reply, chunk in zip(served, in_process_chunks(model.policy, episode, 0), strict=True):
        np.testing.assert_array_equal(reply, chunk)


class PyTorchOnly:
    """A family that exports no graphs: its deployment answers `torch` whatever is asked (`Policy.deployment`)."""

    tasks = None  # single-task

    def deployment(self, checkpoint_path, backend, directory) -> Deployment:
        return Deployment("torch", lambda: self)


def test_a_family_without_graphs_stays_in_pytorch_on_the_onnxruntime_backend(tmp_path):
    policy = PyTorchOnly()
    assert _deployed(policy, tmp_path / "policy.pt", "onnxruntime") == (policy, "torch")


def test_onnxruntime_calls_of_several_robots_run_at_once_and_each_equals_its_graphs_in_process(checkpoint):
    # Top-k sampling, so that each episode's draws from its own generator show in the chunks.
    params = Params(inference={"carp": CarpInference(top_k=4)})
    model, spec = load_served_model(checkpoint, params, backend="onnxruntime")
    assert model.concurrent and not model.batches and model.policy.top_k == 4
    episodes = {robot: observations(12, seed=400 + robot) for robot in range(4)}
    served: dict[int, list[np.ndarray]] = {}
    failures: list[BaseException] = []
    running = ServerThread(PolicyServer(model, spec, ServerSettings(port=0, prediction_threads=2))).start()

    def drive(robot: int) -> None:
        try:
            with PolicyClient(running.url, timeout=30) as client:
                client.reset(seed=robot)
                served[robot] = [client.infer({"obs": obs})["actions"] for obs in episodes[robot]]
        except BaseException as error:  # noqa: BLE001 - re-raised by the test thread below
            failures.append(error)

    threads = [threading.Thread(target=drive, args=(robot,)) for robot in episodes]
    try:
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=120)
        calls = running.policy_server.metrics.model_calls
    finally:
        running.stop()
    assert not failures, failures
    assert calls == 4 * 12  # one call per request
    for robot, episode in episodes.items():
        for reply, chunk in zip(served[robot], in_process_chunks(model.policy, episode, robot), strict=True):
            np.testing.assert_array_equal(reply, chunk)
