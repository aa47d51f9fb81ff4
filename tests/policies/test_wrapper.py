"""The families' shared PyTorch base: one set of checks and conveniences, the same for every family."""

import numpy as np
import pytest
import torch

from carp.config import ConfigError
from carp.data.normalizer import MinMaxNormalizer
from carp.policies.carp.config import CarpConfig, CarpInference
from carp.policies.diffusion.config import DiffusionUNetConfig
from carp.policies.next_token.config import NextTokenConfig, NextTokenInference
from carp.policies.next_token.policy import NextTokenPolicy
from carp.policies.next_token.transformer import NextTokenTransformer
from carp.policies.tasks import DEFAULT_TASK_EMBEDDING_DIM, TASKS_METADATA_KEY
from tests.policies.carp.factories import OBS_DIM, OBS_STEPS, tiny_artifact, tiny_tasks, tiny_tokenizer


def _normalizer(features: int) -> MinMaxNormalizer:
    return MinMaxNormalizer(np.zeros(features), np.ones(features))


def _next_token_policy(num_tasks: int = 0, action_features: int = 2) -> NextTokenPolicy:
    torch.manual_seed(0)
    feature_dim = OBS_DIM + (DEFAULT_TASK_EMBEDDING_DIM if num_tasks else 0)
    transformer = NextTokenTransformer(
        NextTokenConfig(depth=1, width=16, num_heads=2), feature_dim, OBS_STEPS, 2, (1, 2), 8
    )
    artifact = tiny_artifact(tiny_tokenizer())
    obs_normalizer, action_normalizer = _normalizer(OBS_DIM), _normalizer(action_features)
    metadata = {}
    if num_tasks:
        metadata[TASKS_METADATA_KEY] = tiny_tasks(num_tasks, obs_normalizer, action_normalizer).to_dict()
    return NextTokenPolicy(artifact, transformer, obs_normalizer, action_normalizer, metadata)


def test_next_token_task_indices_are_checked_like_carps():
    policy = _next_token_policy(num_tasks=3)
    obs = np.zeros((2, OBS_STEPS, OBS_DIM), dtype=np.float32)
    np.testing.assert_array_equal(policy.predict_action(obs, 2), policy.predict_action(obs, np.array([2, 2])))
    with pytest.raises(ValueError, match="task indices must be in \\[0, 3\\)"):
        policy.predict_action(obs, 3)
    with pytest.raises(ValueError, match="one index or one per sample \\(2\\)"):
        policy.predict_action(obs, [0, 1, 2])
    with pytest.raises(ValueError, match="trained on one task takes no task index"):
        _next_token_policy().predict_action(obs, 0)


def test_an_action_normalizer_of_another_width_is_refused_by_every_family():
    with pytest.raises(ValueError, match="action normalizer has 3 features, the policy predicts A = 2"):
        _next_token_policy(action_features=3)


def test_only_trained_parameters_are_counted():
    policy = _next_token_policy()
    assert policy.num_parameters == sum(parameter.numel() for parameter in policy.transformer.parameters())
    assert all(not parameter.requires_grad for parameter in policy.tokenizer.parameters())


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: CarpConfig(depth=2.0), "carp.depth=2.0: must be an integer >= 1"),
        (lambda: NextTokenConfig(depth=True), "next_token.depth=True: must be an integer >= 1"),
        (lambda: CarpConfig(warmup_steps=1.5), "carp.warmup_steps=1.5: must be an integer >= 0"),
        (lambda: CarpConfig(use_ema=1), "carp.use_ema=1: must be true or false"),
        (lambda: NextTokenConfig(learning_rate=0.0), "next_token.learning_rate=0.0: must be > 0"),
        (lambda: DiffusionUNetConfig(weight_decay=-1.0), "diffusion_unet.weight_decay=-1.0: must be >= 0"),
        (lambda: CarpInference(top_k=2.0), "inference.carp.top_k=2.0: must be an integer >= 1"),
        (lambda: NextTokenInference(top_k_per_task={"can": 0}), "inference.next_token.top_k_per_task.can=0"),
    ],
)
def test_token_families_validate_their_shared_fields_under_their_own_section(make, message):
    with pytest.raises(ConfigError, match=f"^{message}"):
        make()
