"""The policy seam: every family builds from tiny params, trains, saves and loads through `load_policy` unchanged."""

import functools

import numpy as np
import pytest
import torch

from carp.evaluation.sources import PolicySource
from carp.policies.carp.config import CarpConfig
from carp.policies.context import PolicyContext
from carp.policies.registry import (
    build_policy,
    family_names,
    get_family,
    load_policy,
    register_family,
    unregister_family,
)
from carp.training.checkpoint import CheckpointError
from tests.policies.carp.factories import OBS_DIM, OBS_STEPS, tiny_artifact, tiny_policy, tiny_tokenizer
from tests.policies.stub_family import STUB_FAMILY

TINY_CONFIGS = {"carp": CarpConfig(depth=1, width=16, num_heads=2)}


def tiny_context() -> PolicyContext:
    """Do = 3, To = 2, A = 2, H = 8, with the tiny tokenizer of `tests.policies.carp.factories`."""
    policy = tiny_policy()
    return PolicyContext(
        obs_normalizer=policy.obs_normalizer,
        action_normalizer=policy.action_normalizer,
        obs_steps=OBS_STEPS,
        action_horizon=8,
        tokenizer_artifact=tiny_artifact(tiny_tokenizer()),
        metadata={"task": "lift"},
    )


def train_a_few_steps(policy, steps: int = 3) -> list[float]:
    """Adam on the family's own loss over one fixed random batch; returns the losses."""
    generator = torch.Generator().manual_seed(0)
    batch = {
        "obs": torch.rand(16, OBS_STEPS, OBS_DIM, generator=generator) * 2 - 1,
        "actions": torch.rand(16, 8, 2, generator=generator) * 2 - 1,
    }
    trainable = [parameter for parameter in policy.parameters() if parameter.requires_grad]
    optimizer = torch.optim.Adam(trainable, lr=1e-2)
    policy.train()
    losses = []
    for _ in range(steps):
        loss = policy.training_loss(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss))
    policy.train(False)
    return losses


@pytest.fixture(autouse=True)
def stub_registered():
    register_family(STUB_FAMILY)
    yield
    unregister_family(STUB_FAMILY.name)


@pytest.mark.parametrize("name", ["carp", STUB_FAMILY.name])
def test_every_family_round_trips_through_load_policy(name, tmp_path):
    config = TINY_CONFIGS.get(name) or get_family(name).config_class()
    policy = build_policy(name, config, tiny_context())
    losses = train_a_few_steps(policy)
    assert all(np.isfinite(losses)) and losses[-1] < losses[0]
    path = tmp_path / "policy.pt"
    policy.save(path)
    loaded = load_policy(path)
    assert type(loaded) is type(policy) and loaded.policy_type == name
    assert loaded.metadata == {"task": "lift"}
    assert loaded.num_parameters == policy.num_parameters > 0
    obs = np.random.default_rng(1).normal(size=(4, OBS_STEPS, OBS_DIM)).astype(np.float32)
    before = policy.predict_action_timed(obs, generator=torch.Generator().manual_seed(3))
    after = loaded.predict_action_timed(obs, generator=torch.Generator().manual_seed(3))
    np.testing.assert_array_equal(after.actions, before.actions)
    assert before.actions.shape == (4, 8, 2) and before.actions.dtype == np.float32
    assert after.model_calls == loaded.model_calls_per_chunk >= 1


def test_the_stub_family_acts_through_the_evaluation_source(tmp_path):
    policy = build_policy(STUB_FAMILY.name, STUB_FAMILY.config_class(), tiny_context())
    path = tmp_path / "policy.pt"
    policy.save(path)
    deployment = policy.deployment(path, "onnxruntime", tmp_path / "graphs")
    assert deployment.backend == "torch"
    source = PolicySource(deployment.load, controller="delta", obs_steps=OBS_STEPS, action_steps=4)
    source.reset(env=None, seed=0)
    actions, timing = source.act(np.zeros((OBS_STEPS, OBS_DIM)), env=None)
    assert actions.shape == (4, 2) and timing.prediction >= 0


def test_carp_checkpoints_name_their_family(tmp_path):
    path = tmp_path / "policy.pt"
    tiny_policy().save(path)
    checkpoint = torch.load(path, weights_only=True)
    assert checkpoint["policy_type"] == "carp" and checkpoint["format_version"] == 3


def test_an_unknown_family_is_refused_with_the_known_ones_named():
    with pytest.raises(KeyError, match=r"unknown policy family 'lstm' \(known: carp"):
        get_family("lstm")
    assert family_names()[0] == "carp"


def test_a_checkpoint_of_an_unknown_family_is_one_line_naming_the_file(tmp_path):
    path = tmp_path / "policy.pt"
    checkpoint = tiny_policy().to_checkpoint() | {"policy_type": "lstm"}
    torch.save(checkpoint, path)
    with pytest.raises(CheckpointError, match=r"policy_type='lstm': unknown policy family 'lstm'") as raised:
        load_policy(path)
    assert str(raised.value).startswith(f"{path}: ")


def test_inference_settings_are_the_familys_own(tmp_path):
    policy = tiny_policy()
    policy.configure_inference(top_k=3)
    assert policy.description == "top-3"
    with pytest.raises(TypeError, match="num_inference_steps"):
        policy.configure_inference(num_inference_steps=10)
    path = tmp_path / "policy.pt"
    policy.save(path)
    source = functools.partial(PolicySource, functools.partial(load_policy, path), "delta", OBS_STEPS, 4)
    with pytest.raises(ValueError, match="top_k"):
        source(inference={"top_k": 99})
