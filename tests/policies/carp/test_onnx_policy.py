"""The ONNX Runtime fast path must choose the same tokens and return the same actions as the PyTorch policy."""

import functools

import numpy as np
import pytest
import torch

from carp.evaluation.runner import deploy
from carp.evaluation.sources import PolicySource
from carp.policies.carp import onnx_policy as onnx_module
from carp.policies.carp.onnx_policy import OnnxPolicy, export_policy_graphs
from carp.policies.carp.sampling import generate_chunk
from carp.policies.registry import load_policy
from carp.tasks.arms.task import DELTA_ACTIONS
from tests.policies.carp.factories import OBS_DIM, OBS_STEPS, tiny_policy

SCALES = (1, 2, 4)


def torch_tokens(
    policy, obs: np.ndarray, task_index: int | None = None, top_k: int = 1, seed: int | None = None
) -> np.ndarray:
    """The token sequence (1, L) of the PyTorch path (greedy, or top-k with a generator seeded with `seed`)."""
    generator = None if seed is None else torch.Generator().manual_seed(seed)
    with torch.inference_mode():
        features = policy.observation_features(obs, OBS_STEPS, task_index=task_index)
        chunk = generate_chunk(policy.transformer, policy.tokenizer, features, top_k, generator)
        return policy.tokenizer.ids_to_sequence(chunk.token_ids).numpy()


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    policy = tiny_policy(SCALES, depth=2)
    directory = export_policy_graphs(policy, tmp_path_factory.mktemp("onnx"))
    return policy, OnnxPolicy(directory)


def test_greedy_tokens_and_actions_match_the_torch_policy(exported):
    policy, onnx_policy = exported
    rng = np.random.default_rng(1)
    distinct = set()
    for _ in range(8):
        obs = rng.normal(size=(1, OBS_STEPS, OBS_DIM)) * 3
        tokens = onnx_policy.predict_tokens(obs)
        assert tokens.shape == (1, policy.spec.sequence_length)
        np.testing.assert_array_equal(tokens, torch_tokens(policy, obs))
        timed = onnx_policy.predict_action_timed(obs)
        np.testing.assert_allclose(timed.actions, policy.predict_action(obs), rtol=1e-5, atol=1e-5)
        assert timed.prediction_seconds > 0 and timed.decoding_seconds > 0
        distinct.add(tokens.tobytes())
    assert len(distinct) > 1, "observations should change the chosen tokens"


@pytest.mark.parametrize("scales", [(1,), (1, 2), (1, 2, 3), (1, 2, 3, 4, 5), (1, 2, 3, 4, 5, 6)])
def test_every_scale_schedule_exports_a_graph_that_matches_pytorch(scales, tmp_path):
    # H = 16 as in the pipeline: the encoder's latent is 4 long, so these schedules end below it, and above it.
    policy = tiny_policy(scales, seed=2, action_horizon=16)
    assert policy.tokenizer.spec.latent_length == max(4, scales[-1])
    onnx_policy = OnnxPolicy(export_policy_graphs(policy, tmp_path))
    rng = np.random.default_rng(3)
    for _ in range(4):
        obs = rng.normal(size=(1, OBS_STEPS, OBS_DIM)) * 3
        tokens = onnx_policy.predict_tokens(obs)
        assert tokens.shape == (1, 2 * sum(scales))
        np.testing.assert_array_equal(tokens, torch_tokens(policy, obs))
        actions = onnx_policy.predict_action_timed(obs).actions
        assert actions.shape == (1, 16, 2)
        np.testing.assert_allclose(actions, policy.predict_action(obs), rtol=1e-5, atol=1e-5)


def test_top_k_graph_draws_the_tokens_the_torch_policy_draws_with_the_same_generator(exported, tmp_path):
    policy, greedy_onnx = exported
    sampling = OnnxPolicy(export_policy_graphs(policy, tmp_path, top_k=3))
    assert (sampling.top_k, greedy_onnx.top_k) == (3, 1)
    obs = np.random.default_rng(4).normal(size=(1, OBS_STEPS, OBS_DIM)) * 3
    greedy = greedy_onnx.predict_tokens(obs)
    draws = []
    for seed in range(6):
        tokens = sampling.predict_tokens(obs, generator=torch.Generator().manual_seed(seed))
        np.testing.assert_array_equal(tokens, torch_tokens(policy, obs, top_k=3, seed=seed))
        timed = sampling.predict_action_timed(obs, generator=torch.Generator().manual_seed(seed))
        expected = policy.predict_action(obs, top_k=3, generator=torch.Generator().manual_seed(seed))
        np.testing.assert_allclose(timed.actions, expected, rtol=1e-5, atol=1e-5)
        draws.append(tokens)
    # Seeds change the draws, and the draws leave the greedy choice at some positions.
    assert len({tokens.tobytes() for tokens in draws}) > 1
    assert all((tokens != greedy).any() for tokens in draws)


def test_multi_task_graph_takes_the_task_index(tmp_path):
    policy = tiny_policy(SCALES, num_tasks=3)
    onnx_policy = OnnxPolicy(export_policy_graphs(policy, tmp_path))
    obs = np.random.default_rng(2).normal(size=(1, OBS_STEPS, OBS_DIM))
    for task_index in (0, 2):
        expected = torch_tokens(policy, obs, task_index)
        np.testing.assert_array_equal(onnx_policy.predict_tokens(obs, task_index), expected)
    # Without an index the graph runs the task the policy had selected when it was exported.
    np.testing.assert_array_equal(onnx_policy.predict_tokens(obs), torch_tokens(policy, obs, 0))
    policy.select_task("task2")
    selected = OnnxPolicy(export_policy_graphs(policy, tmp_path / "task2"))
    np.testing.assert_array_equal(selected.predict_tokens(obs), torch_tokens(policy, obs))
    np.testing.assert_allclose(selected.predict_action(obs), policy.predict_action(obs), rtol=1e-4, atol=1e-4)
    policy.select_task("task0")
    sampling = OnnxPolicy(export_policy_graphs(policy, tmp_path / "top2", top_k=2))
    for task_index in (0, 2):
        drawn = sampling.predict_tokens(obs, task_index, generator=torch.Generator().manual_seed(task_index))
        np.testing.assert_array_equal(drawn, torch_tokens(policy, obs, task_index, top_k=2, seed=task_index))


def test_a_padded_task_takes_its_own_observations_in_pytorch_and_in_its_graph(tmp_path):
    # Lift's keys are 1 and 1 wide, Can's 1 and 2: Lift's observations sit in the first two of the three columns.
    widths = {"lift": (1, 1), "can": (1, 2)}
    policy = tiny_policy(SCALES, seed=4, num_tasks=2, task_names=("lift", "can"), obs_widths=widths)
    own = np.random.default_rng(5).normal(size=(1, OBS_STEPS, 2))
    padded = np.concatenate([own, np.zeros((1, OBS_STEPS, 1))], axis=-1)
    np.testing.assert_array_equal(torch_tokens(policy, own), torch_tokens(policy, padded))
    np.testing.assert_array_equal(policy.predict_action(own), policy.predict_action(padded))
    graph = OnnxPolicy(export_policy_graphs(policy, tmp_path / "lift"))
    np.testing.assert_array_equal(graph.predict_tokens(own), torch_tokens(policy, own))
    np.testing.assert_allclose(graph.predict_action(own), policy.predict_action(own), rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match=r"obs of task 'lift' must have its own 2 features \(or the padded 3\)"):
        policy.predict_action(np.zeros((1, OBS_STEPS, 4)))
    # Can has the padded layout itself: its graph takes all three columns.
    policy.select_task("can")
    can_obs = np.random.default_rng(6).normal(size=(1, OBS_STEPS, OBS_DIM))
    can_graph = OnnxPolicy(export_policy_graphs(policy, tmp_path / "can"))
    np.testing.assert_array_equal(can_graph.predict_tokens(can_obs), torch_tokens(policy, can_obs))


def test_bad_inputs_are_refused(exported):
    _, onnx_policy = exported
    with pytest.raises(ValueError, match=r"obs must have shape \(1, 2, 3\) \(one environment\), got \(2, 2, 3\)"):
        onnx_policy.predict_action_timed(np.zeros((2, OBS_STEPS, OBS_DIM)))
    with pytest.raises(ValueError, match="single-task but a task index was given"):
        onnx_policy.predict_action_timed(np.zeros((1, OBS_STEPS, OBS_DIM)), task_index=0)


def test_policy_source_acts_the_same_on_both_backends(exported, tmp_path):
    policy, _ = exported
    checkpoint = tmp_path / "policy.pt"
    policy.save(checkpoint)
    directory = export_policy_graphs(policy, tmp_path / "onnx")
    settings = dict(action_format=DELTA_ACTIONS, obs_steps=OBS_STEPS, action_steps=4)
    on_torch = PolicySource(functools.partial(load_policy, checkpoint), **settings)
    on_onnx = PolicySource(functools.partial(OnnxPolicy, directory), **settings)
    history = np.random.default_rng(3).normal(size=(OBS_STEPS, OBS_DIM))
    actions_torch, _ = on_torch.act(history, env=None)
    actions_onnx, timing = on_onnx.act(history, env=None)
    np.testing.assert_allclose(actions_onnx, actions_torch, rtol=1e-5, atol=1e-5)
    assert timing.prediction > 0
    with pytest.raises(ValueError, match=r"use top_k = 1, got top_k = 4"):
        PolicySource(functools.partial(OnnxPolicy, directory), **settings, inference={"top_k": 4})


def test_onnx_policy_reports_the_facts_of_the_policy_it_was_exported_from(exported):
    policy, onnx_policy = exported
    assert onnx_policy.model_calls_per_chunk == policy.model_calls_per_chunk == len(SCALES)
    assert onnx_policy.num_parameters == policy.num_parameters > 0
    assert onnx_policy.policy_type == policy.policy_type == "carp"
    assert onnx_policy.metadata == policy.metadata
    timed = onnx_policy.predict_action_timed(np.zeros((1, OBS_STEPS, OBS_DIM), dtype=np.float32))
    assert timed.model_calls == len(SCALES)


def test_deployment_exports_for_onnx_runs_and_falls_back_to_torch(exported, tmp_path, monkeypatch, caplog):
    policy, _ = exported
    checkpoint = tmp_path / "policy.pt"
    policy.save(checkpoint)
    deployment = policy.deployment(checkpoint, "onnxruntime", tmp_path / "graphs")
    assert deployment.backend == "onnxruntime" and (tmp_path / "graphs" / "prediction.onnx").is_file()
    assert isinstance(deployment.load(), OnnxPolicy)
    on_torch = policy.deployment(checkpoint, "torch", tmp_path / "unused")
    assert on_torch.backend == "torch" and on_torch.load is None and not (tmp_path / "unused").exists()
    # Evaluation fills in the loading of the checkpoint itself.
    assert deploy(policy, checkpoint, "torch", tmp_path / "unused").load().policy_type == "carp"
    policy.configure_inference(top_k=4)
    try:
        sampling = policy.deployment(checkpoint, "onnxruntime", tmp_path / "sampling")
    finally:
        policy.configure_inference(top_k=1)
    assert sampling.load().top_k == 4

    def broken_export(*args, **kwargs):
        raise RuntimeError("unsupported operator")

    monkeypatch.setattr(onnx_module, "export_policy_graphs", broken_export)
    fallback = policy.deployment(checkpoint, "onnxruntime", tmp_path / "broken")
    assert fallback.backend == "torch"
    assert "ONNX export of" in caplog.text and "RuntimeError: unsupported operator" in caplog.text
    assert not (tmp_path / "broken").exists()
