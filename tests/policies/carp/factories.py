"""Tiny tokenizer, transformer and training factories shared by the policy and policy-trainer tests."""

import dataclasses

import numpy as np
import torch

from carp.config import TrainingConfig
from carp.data.normalizer import MinMaxNormalizer
from carp.data.obs_padding import padded_layout
from carp.policies.carp.config import CarpConfig
from carp.policies.carp.family import train
from carp.policies.carp.policy import CarpPolicy
from carp.policies.carp.spec import PolicySpec
from carp.policies.carp.transformer import CoarseToFineTransformer
from carp.policies.context import PolicyContext
from carp.policies.registry import TrainingRun
from carp.policies.tasks import DEFAULT_TASK_EMBEDDING_DIM, TASKS_METADATA_KEY, PolicyTasks
from carp.tokenizer.artifact import TokenizerArtifact
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer

OBS_STEPS = 2
OBS_DIM = 3
TINY_ARCHITECTURE = dict(depth=1, width=16, num_heads=2)
"""The CARP params of :func:`tiny_policy_spec`'s transformer."""


def tiny_tokenizer_spec(scales: tuple[int, ...] = (1, 2), action_horizon: int | None = None) -> TokenizerSpec:
    """A = 2, V = 8, C = 4; H = 4 * s_K (the encoder's length is the last scale) unless `action_horizon` is given."""
    horizon = 4 * scales[-1] if action_horizon is None else action_horizon
    return TokenizerSpec(action_dim=2, action_horizon=horizon, scales=scales, codebook_size=8, latent_channels=4)


def tiny_policy_spec(scales: tuple[int, ...] = (1, 2), **overrides) -> PolicySpec:
    """Depth 1, D = 16, 2 heads, matching :func:`tiny_tokenizer_spec`; `CarpConfig` keys among `overrides` go to
    the config, the others to the shapes."""
    config_keys = {field.name for field in dataclasses.fields(CarpConfig)}
    config = TINY_ARCHITECTURE | {key: value for key, value in overrides.items() if key in config_keys}
    shapes = dict(obs_dim=OBS_DIM, obs_steps=OBS_STEPS, action_dim=2, scales=scales, latent_channels=4, codebook_size=8)
    shapes.update({key: value for key, value in overrides.items() if key not in config_keys})
    return PolicySpec(**shapes, config=CarpConfig(**config))


def tiny_tokenizer(
    scales: tuple[int, ...] = (1, 2), seed: int = 0, action_horizon: int | None = None
) -> MultiScaleActionTokenizer:
    """A randomly initialized tokenizer whose codes are spread out enough to give distinct tokens."""
    torch.manual_seed(seed)
    tokenizer = MultiScaleActionTokenizer(tiny_tokenizer_spec(scales, action_horizon))
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


def tiny_tasks(
    num_tasks: int,
    obs_normalizer: MinMaxNormalizer,
    action_normalizer: MinMaxNormalizer,
    names: tuple[str, ...] | None = None,
    obs_widths: dict[str, tuple[int, ...]] | None = None,
) -> PolicyTasks:
    """Tasks `names` (default `task0`, `task1`, ...); task i's statistics are the given ones shifted by i (the first
    selected). With `obs_widths` (task -> its widths per key, padding to `obs_normalizer`'s width), a task keeps the
    statistics of its own columns, padded (`carp.data.obs_padding`)."""
    names = names or tuple(f"task{index}" for index in range(num_tasks))

    def shifted(normalizer: MinMaxNormalizer, shift: float) -> MinMaxNormalizer:
        return MinMaxNormalizer(normalizer.minimum + shift, normalizer.maximum + shift)

    obs_normalizers = {name: shifted(obs_normalizer, index) for index, name in enumerate(names)}
    if obs_widths is not None:
        for name, padding in padded_layout(obs_widths).items():
            own = obs_normalizers[name]
            columns = padding.positions()
            obs_normalizers[name] = padding.pad_normalizer(MinMaxNormalizer(own.minimum[columns], own.maximum[columns]))
    return PolicyTasks(
        names,
        obs_normalizers,
        {name: shifted(action_normalizer, index) for index, name in enumerate(names)},
        obs_widths=obs_widths,
    )


def tiny_policy(
    scales: tuple[int, ...] = (1, 2),
    seed: int = 0,
    num_tasks: int = 0,
    task_names: tuple[str, ...] | None = None,
    obs_widths: dict[str, tuple[int, ...]] | None = None,
    action_horizon: int | None = None,
    **overrides,
) -> CarpPolicy:
    """Scrambled transformer + random tokenizer + normalizers (the second action feature is constant).

    With `num_tasks`, a multi-task policy over :func:`tiny_tasks` named `task_names` (its features F = Do + the task
    embedding), whose tasks' own obs widths are `obs_widths` (:func:`tiny_tasks`).
    """
    rng = np.random.default_rng(seed)
    obs_min = rng.normal(size=OBS_DIM)
    action_min = np.array([-2.0, 0.5])
    obs_normalizer = MinMaxNormalizer(obs_min, obs_min + rng.uniform(0.5, 2.0, size=OBS_DIM))
    action_normalizer = MinMaxNormalizer(action_min, np.array([3.0, 0.5]))
    metadata = {"tokenizer_ref": {"name": "carp-tokenizer-test", "version": 1}}
    if num_tasks:
        tasks = tiny_tasks(num_tasks, obs_normalizer, action_normalizer, task_names, obs_widths)
        metadata[TASKS_METADATA_KEY] = tasks.to_dict()
        obs_normalizer = tasks.obs_normalizers[tasks.selected]
        overrides = {"obs_dim": OBS_DIM + DEFAULT_TASK_EMBEDDING_DIM} | overrides
    return CarpPolicy(
        tiny_artifact(tiny_tokenizer(scales, seed, action_horizon)),
        scrambled_transformer(tiny_policy_spec(scales, **overrides), seed),
        obs_normalizer,
        action_normalizer,
        metadata=metadata,
    )


def tiny_context(tokenizer: MultiScaleActionTokenizer, num_tasks: int = 0) -> PolicyContext:
    """Do = 3, To = 2, observations and actions in [-1, 1], and `tokenizer` (A = 2) as the registered one."""
    action_dim = tokenizer.spec.action_dim
    obs_normalizer = MinMaxNormalizer(np.full(OBS_DIM, -1.0), np.full(OBS_DIM, 1.0))
    action_normalizer = MinMaxNormalizer(np.full(action_dim, -1.0), np.full(action_dim, 1.0))
    return PolicyContext(
        obs_normalizer=obs_normalizer,
        action_normalizer=action_normalizer,
        obs_steps=OBS_STEPS,
        action_horizon=tokenizer.spec.action_horizon,
        tokenizer_artifact=tiny_artifact(tokenizer),
        tasks=tiny_tasks(num_tasks, obs_normalizer, action_normalizer) if num_tasks else None,
    )


def train_carp(tokenizer, data, settings: dict, checkpoint_dir, on_epoch_end=None, num_tasks: int = 0) -> CarpPolicy:
    """The CARP family's `train` on :func:`tiny_context`, its config and loop settings given as one flat mapping.

    Keys of `CarpConfig` go to the config (the architecture defaults to `TINY_ARCHITECTURE`), keys of
    `TrainingConfig` to the loop, `device` (default cpu) to the device.
    """
    settings = trainer_settings(**(TINY_ARCHITECTURE | settings))
    data_and_state = dict(context=tiny_context(tokenizer, num_tasks), data=data, checkpoint_dir=checkpoint_dir)
    run = TrainingRun(settings["training"], device=settings["device"], on_epoch_end=on_epoch_end, **data_and_state)
    return train(settings["config"], run)


def trainer_settings(device: str = "cpu", **values) -> dict:
    """Keyword arguments `config`, `training` and `device` of the trainer from one flat mapping of settings."""
    config_keys = {field.name for field in dataclasses.fields(CarpConfig)}
    # One kernel unless a test asks for another: several tests compare two trainings bit for bit, and `auto` may
    # time the kernels differently in each.
    values = {"attention": "masked"} | values
    return {
        "config": CarpConfig(**{key: value for key, value in values.items() if key in config_keys}),
        "training": TrainingConfig(**{key: value for key, value in values.items() if key not in config_keys}),
        "device": device,
    }
