"""Tiny VQ-BeT configs, contexts and windows shared by the family's tests."""

import numpy as np
import torch

from carp.data.normalizer import MinMaxNormalizer
from carp.policies.context import PolicyContext
from carp.policies.vq_bet.config import VqBetConfig
from carp.training.loop import PolicyTrainingData

OBS_DIM, OBS_STEPS, HORIZON, ACTION_DIM = 5, 2, 8, 2


def tiny_config(**overrides) -> VqBetConfig:
    """A VQ-BeT small enough for unit tests: 4 codes x 2 layers, one GPT layer of width 16."""
    settings = dict(
        num_codes=4,
        latent_width=8,
        encoder_hidden_width=16,
        vq_training_steps=5,
        vq_batch_size=8,
        depth=1,
        num_heads=2,
        width=16,
        output_width=16,
        head_hidden_width=32,
        learning_rate=1e-3,
    )
    return VqBetConfig(**(settings | overrides))


def tiny_context() -> PolicyContext:
    """Observations of Do = 5 features and actions of A = 2, To = 2, H = 8, single-task."""
    return PolicyContext(
        obs_normalizer=MinMaxNormalizer(np.full(OBS_DIM, -2.0), np.full(OBS_DIM, 2.0)),
        action_normalizer=MinMaxNormalizer(np.full(ACTION_DIM, -1.0), np.full(ACTION_DIM, 3.0)),
        obs_steps=OBS_STEPS,
        action_horizon=HORIZON,
        metadata={"task": "pusht"},
    )


def tiny_data(count: int = 24, seed: int = 0) -> PolicyTrainingData:
    """`count` random normalized windows."""
    generator = torch.Generator().manual_seed(seed)
    obs = torch.rand(count, OBS_STEPS, OBS_DIM, generator=generator) * 2 - 1
    actions = torch.rand(count, HORIZON, ACTION_DIM, generator=generator) * 2 - 1
    return PolicyTrainingData(obs, actions)
