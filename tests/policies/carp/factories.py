"""Tiny tokenizer and transformer factories shared by the policy and policy-trainer tests."""

import dataclasses

import numpy as np
import torch

from carp.config import TrainingConfig
from carp.data.normalizer import MinMaxNormalizer
from carp.policies.carp.config import CarpConfig
from carp.policies.carp.policy import CarpPolicy
from carp.policies.carp.spec import PolicySpec
from carp.policies.carp.trainer import train_policy
from carp.policies.carp.transformer import CoarseToFineTransformer
from carp.tokenizer.artifact import TokenizerArtifact
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer

OBS_STEPS = 2
OBS_DIM = 3


def tiny_tokenizer_spec(scales: tuple[int, ...] = (1, 2)) -> TokenizerSpec:
    """A = 2, V = 8, C = 4; H = 4 * s_K so the latent length equals the last scale."""
    return TokenizerSpec(action_dim=2, action_horizon=4 * scales[-1], scales=scales, codebook_size=8, latent_channels=4)


def tiny_policy_spec(scales: tuple[int, ...] = (1, 2), **overrides) -> PolicySpec:
    """Depth 1, D = 16, 2 heads, matching :func:`tiny_tokenizer_spec`."""
    values = dict(
        obs_dim=OBS_DIM,
        obs_steps=OBS_STEPS,
        action_dim=2,
        scales=scales,
        latent_channels=4,
        codebook_size=8,
        depth=1,
        width=16,
        num_heads=2,
    )
    values.update(overrides)
    return PolicySpec(**values)


def tiny_tokenizer(scales: tuple[int, ...] = (1, 2), seed: int = 0) -> MultiScaleActionTokenizer:
    """A randomly initialized tokenizer whose codes are spread out enough to give distinct tokens."""
    torch.manual_seed(seed)
    tokenizer = MultiScaleActionTokenizer(tiny_tokenizer_spec(scales))
    with torch.no_grad():
        tokenizer.quantizer.codebook.normal_()
    return tokenizer.eval()


def tiny_artifact(tokenizer: MultiScaleActionTokenizer) -> TokenizerArtifact:
    """`tokenizer` with the statistics of one training task (A = 2) and a test action space."""
    normalizer = MinMaxNormalizer(np.array([-2.0, 0.5]), np.array([3.0, 0.5]))
    return TokenizerArtifact.build(tokenizer, {"task": normalizer}, "test-abs2")


def scrambled_transformer(spec: PolicySpec, seed: int = 0) -> CoarseToFineTransformer:
    """A transformer with large random weights, so logits differ clearly between tokens and inputs matter.

    The default initialization starts every block near the identity with near-uniform logits, which would make
    equivalence tests pass trivially.
    """
    torch.manual_seed(seed)
    transformer = CoarseToFineTransformer(spec)
    with torch.no_grad():
        for parameter in transformer.parameters():
            parameter.normal_(0.0, 0.2)
    return transformer.eval()


def tiny_policy(scales: tuple[int, ...] = (1, 2), seed: int = 0, **overrides) -> CarpPolicy:
    """Scrambled transformer + random tokenizer + normalizers (the second action feature is constant)."""
    rng = np.random.default_rng(seed)
    obs_min = rng.normal(size=OBS_DIM)
    action_min = np.array([-2.0, 0.5])
    return CarpPolicy(
        tiny_artifact(tiny_tokenizer(scales, seed)),
        scrambled_transformer(tiny_policy_spec(scales, **overrides), seed),
        MinMaxNormalizer(obs_min, obs_min + rng.uniform(0.5, 2.0, size=OBS_DIM)),
        MinMaxNormalizer(action_min, np.array([3.0, 0.5])),
        metadata={"tokenizer_ref": {"name": "carp-tokenizer-test", "version": 1}},
    )


def train_transformer(spec, tokenizer, data, settings: dict, checkpoint_dir, on_epoch_end=None):
    """`carp.policies.carp.trainer.train_policy` with its config and loop settings given as one flat mapping.

    Keys of `CarpConfig` go to the config, keys of `TrainingConfig` to the loop, `device` (default cpu) to the device.
    """
    return train_policy(
        spec, tokenizer, data, checkpoint_dir=checkpoint_dir, on_epoch_end=on_epoch_end, **trainer_settings(**settings)
    )


def trainer_settings(device: str = "cpu", **values) -> dict:
    """Keyword arguments `config`, `training` and `device` of the trainer from one flat mapping of settings."""
    config_keys = {field.name for field in dataclasses.fields(CarpConfig)}
    return {
        "config": CarpConfig(**{key: value for key, value in values.items() if key in config_keys}),
        "training": TrainingConfig(**{key: value for key, value in values.items() if key not in config_keys}),
        "device": device,
    }
