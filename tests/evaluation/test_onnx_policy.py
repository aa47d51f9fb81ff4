"""The ONNX Runtime fast path must choose the same tokens and return the same actions as the PyTorch policy."""

import numpy as np
import pytest
import torch

from carp.evaluation import runner
from carp.evaluation.onnx_policy import OnnxGreedyPolicy, export_greedy_policy
from carp.evaluation.runner import onnx_graphs_for
from carp.evaluation.sources import PolicySource
from carp.policy.sampling import generate_chunk
from tests.policy.factories import OBS_DIM, OBS_STEPS, tiny_policy

SCALES = (1, 2, 4)


def torch_tokens(policy, obs: np.ndarray, task_index: int | None = None) -> np.ndarray:
    """The greedy token sequence (1, L) of the PyTorch path."""
    with torch.inference_mode():
        observations = policy.obs_normalizer.normalize(torch.as_tensor(obs, dtype=torch.float32))
        task_ids = None if task_index is None else torch.tensor([task_index])
        chunk = generate_chunk(policy.transformer, policy.tokenizer, observations, task_ids)
        return policy.tokenizer.ids_to_sequence(chunk.token_ids).numpy()


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    policy = tiny_policy(SCALES, depth=2)
    directory = export_greedy_policy(policy, tmp_path_factory.mktemp("onnx"))
    return policy, OnnxGreedyPolicy(directory)


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


def test_multi_task_graph_takes_the_task_index(tmp_path):
    policy = tiny_policy(SCALES, num_tasks=3)
    onnx_policy = OnnxGreedyPolicy(export_greedy_policy(policy, tmp_path))
    obs = np.random.default_rng(2).normal(size=(1, OBS_STEPS, OBS_DIM))
    for task_index in (0, 2):
        expected = torch_tokens(policy, obs, task_index)
        np.testing.assert_array_equal(onnx_policy.predict_tokens(obs, task_index), expected)
    with pytest.raises(ValueError, match="needs a task index"):
        onnx_policy.predict_action_timed(obs)


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
    directory = export_greedy_policy(policy, tmp_path / "onnx")
    settings = dict(controller="delta", obs_steps=OBS_STEPS, action_steps=4)
    on_torch = PolicySource(checkpoint, **settings)
    on_onnx = PolicySource(checkpoint, **settings, onnx_directory=directory)
    history = np.random.default_rng(3).normal(size=(OBS_STEPS, OBS_DIM))
    actions_torch, _ = on_torch.act(history, env=None)
    actions_onnx, timing = on_onnx.act(history, env=None)
    np.testing.assert_allclose(actions_onnx, actions_torch, rtol=1e-5, atol=1e-5)
    assert timing.prediction > 0
    with pytest.raises(ValueError, match="greedy"):
        PolicySource(checkpoint, **settings, top_k=4, onnx_directory=directory)


def test_evaluation_exports_only_for_greedy_onnx_runs_and_falls_back_to_torch(exported, tmp_path, monkeypatch, caplog):
    policy, _ = exported
    checkpoint = tmp_path / "policy.pt"
    policy.save(checkpoint)
    directory = onnx_graphs_for(checkpoint, "onnxruntime", 1, tmp_path / "graphs")
    assert directory == tmp_path / "graphs" and (directory / "prediction.onnx").is_file()
    assert onnx_graphs_for(checkpoint, "torch", 1, tmp_path / "unused") is None
    assert onnx_graphs_for(checkpoint, "onnxruntime", 4, tmp_path / "unused") is None
    with pytest.raises(ValueError, match="backend must be 'onnxruntime' or 'torch', got 'tvm'"):
        onnx_graphs_for(checkpoint, "tvm", 1, tmp_path / "unused")

    def broken_export(*args, **kwargs):
        raise RuntimeError("unsupported operator")

    monkeypatch.setattr(runner, "export_greedy_policy", broken_export)
    assert onnx_graphs_for(checkpoint, "onnxruntime", 1, tmp_path / "unused") is None
    assert "ONNX export of" in caplog.text and "RuntimeError: unsupported operator" in caplog.text
    assert not (tmp_path / "unused").exists()
