"""The VQ-BeT GPT and policy: the official size, prediction, code choice, the loss and its freeze."""

import numpy as np
import pytest
import torch

from carp.policies.base import Policy
from carp.policies.vq_bet.config import VqBetConfig
from carp.policies.vq_bet.family import build
from carp.policies.vq_bet.transformer import BehaviorTransformer
from tests.policies.vq_bet.factories import HORIZON, OBS_DIM, OBS_STEPS, tiny_config, tiny_context, tiny_data


def test_official_push_t_size():
    """Push-T's state (Do = 20, A = 2) at the defaults: 4,787,816 at carp's H = 16, 4,263,016 at H = 8."""
    assert sum(p.numel() for p in BehaviorTransformer(VqBetConfig(), 20, 2, 16, 2).parameters()) == 4_787_816
    assert sum(p.numel() for p in BehaviorTransformer(VqBetConfig(), 20, 2, 8, 2).parameters()) == 4_263_016


def built_policy():
    torch.manual_seed(0)
    policy = build(tiny_config(), tiny_context())
    data = tiny_data()
    policy.autoencoder.quantizer.initialize(policy.autoencoder.encode_to_latent(data.actions))
    return policy.train(False)


def raw_obs(batch: int = 3) -> np.ndarray:
    return np.random.default_rng(0).uniform(-2, 2, size=(batch, OBS_STEPS, OBS_DIM)).astype(np.float32)


def test_policy_is_a_policy_and_counts_only_trained_parameters():
    policy = built_policy()
    assert isinstance(policy, Policy)
    assert policy.num_parameters == sum(p.numel() for p in policy.transformer.parameters())
    assert not policy.autoencoder.training and policy.model_calls_per_chunk == 1


def test_sampling_follows_the_generator_and_greedy_ignores_it():
    policy = built_policy()
    obs = raw_obs()
    first = policy.predict_action(obs, generator=torch.Generator().manual_seed(7))
    again = policy.predict_action(obs, generator=torch.Generator().manual_seed(7))
    assert first.shape == (3, HORIZON, 2) and first.dtype == np.float32
    np.testing.assert_array_equal(first, again)
    draws = {policy.predict_action(obs, generator=torch.Generator().manual_seed(s)).tobytes() for s in range(8)}
    assert len(draws) > 1
    policy.configure_inference(code_choice="greedy")
    assert policy.description == "greedy"
    greedy = [policy.predict_action(obs, generator=torch.Generator().manual_seed(s)) for s in range(2)]
    np.testing.assert_array_equal(greedy[0], greedy[1])


def test_greedy_actions_are_decoded_codes_plus_their_offset():
    policy = built_policy()
    policy.configure_inference(code_choice="greedy")
    obs = raw_obs()
    actions = policy.predict_action(obs)
    with torch.no_grad():
        features = policy.transformer.features(policy.observation_features(obs, OBS_STEPS))
        codes = policy.transformer.code_logits(features).argmax(-1)
        normalized = policy.autoencoder.decode_ids(codes) + policy.transformer.code_offsets(features, codes)
    np.testing.assert_allclose(actions, policy.action_normalizer.unnormalize(normalized).numpy(), rtol=1e-5, atol=1e-5)


def test_bad_inputs_are_refused():
    policy = built_policy()
    with pytest.raises(ValueError, match="trained on one task takes no task index"):
        policy.predict_action(raw_obs(), task_index=0)
    with pytest.raises(ValueError, match="code_choice"):
        policy.configure_inference(code_choice="top-3")
    with pytest.raises(ValueError, match=r"\(B, To, Do\)"):
        policy.predict_action(raw_obs()[:, :1])


def test_frozen_phase_trains_only_the_offset_head_and_counts_steps():
    policy = built_policy().train()
    data = tiny_data()
    batch = {"obs": data.obs[:8], "actions": data.actions[:8]}
    policy.freeze_after_steps = 1
    policy.training_loss(batch).backward()
    assert policy.transformer.code_head[0].weight.grad is not None
    policy.zero_grad(set_to_none=True)
    loss = policy.training_loss(batch)
    loss.backward()
    assert int(policy.trained_steps) == 2 and torch.isfinite(loss)
    gpt = [p for module in policy.transformer.gpt_modules() for p in module.parameters()]
    assert all(p.grad is None for p in gpt)
    assert all(p.grad is not None for p in policy.transformer.offset_head.parameters())
    assert all(p.grad is None for p in policy.autoencoder.parameters())
