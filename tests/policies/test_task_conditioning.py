"""Multi-task conditioning: one task embedding in the shared observation encoder, for every family."""

import json

import numpy as np
import pytest
import torch

from carp.data.normalizer import MinMaxNormalizer
from carp.policies.carp.config import CarpConfig
from carp.policies.context import PolicyContext
from carp.policies.diffusion.config import DiffusionTransformerConfig, DiffusionUNetConfig
from carp.policies.next_token.config import NextTokenConfig
from carp.policies.observations import StateObservations, TaskConditionedObservations, build_observation_encoder
from carp.policies.registry import build_policy, load_policy
from carp.policies.tasks import PolicyTasks
from tests.policies.carp.factories import OBS_DIM, OBS_STEPS, tiny_artifact, tiny_tasks, tiny_tokenizer
from tests.policies.vq_bet.factories import tiny_config as tiny_vq_bet_config

TINY_SECTIONS = {
    "carp": CarpConfig(depth=1, width=16, num_heads=2),
    "next_token": NextTokenConfig(depth=1, width=16, num_heads=2),
    "diffusion_unet": DiffusionUNetConfig(
        down_dims=(16, 32), kernel_size=3, num_groups=8, step_embedding_dim=16, num_train_steps=4
    ),
    "diffusion_transformer": DiffusionTransformerConfig(num_layers=1, num_heads=2, width=16, num_train_steps=4),
    "vq_bet": tiny_vq_bet_config(),
}


def _context(num_tasks: int, obs_widths: dict[str, tuple[int, ...]] | None = None) -> PolicyContext:
    tokenizer = tiny_tokenizer()
    obs_normalizer = MinMaxNormalizer(np.full(OBS_DIM, -1.0), np.full(OBS_DIM, 1.0))
    action_normalizer = MinMaxNormalizer(np.full(2, -1.0), np.full(2, 1.0))
    tasks = None
    if num_tasks:
        names = None if obs_widths is None else tuple(obs_widths)
        tasks = tiny_tasks(num_tasks, obs_normalizer, action_normalizer, names, obs_widths)
    return PolicyContext(
        obs_normalizer=obs_normalizer if tasks is None else tasks.obs_normalizers[tasks.selected],
        action_normalizer=action_normalizer,
        obs_steps=OBS_STEPS,
        action_horizon=tokenizer.spec.action_horizon,
        tokenizer_artifact=tiny_artifact(tokenizer),
        tasks=tasks,
    )


def test_identical_observations_of_two_tasks_give_different_features():
    torch.manual_seed(0)
    encoder = build_observation_encoder(OBS_DIM, None, num_tasks=2, task_embedding_dim=3)
    assert isinstance(encoder, TaskConditionedObservations) and encoder.output_dim == OBS_DIM + 3
    obs = torch.randn(1, OBS_STEPS, OBS_DIM).expand(2, -1, -1)  # the same observations for both tasks
    features = encoder(obs, None, torch.tensor([0, 1]))  # (2, To, Do + 3)
    assert features.shape == (2, OBS_STEPS, OBS_DIM + 3)
    torch.testing.assert_close(features[:, :, :OBS_DIM], obs)
    # Every step carries its task's embedding row, and the two rows differ.
    for task in (0, 1):
        torch.testing.assert_close(
            features[task, :, OBS_DIM:], encoder.task_embedding.weight[task].expand(OBS_STEPS, -1)
        )
    assert (features[0, :, OBS_DIM:] - features[1, :, OBS_DIM:]).abs().min() > 1e-3
    with pytest.raises(ValueError, match="multi-task \\(2 tasks\\): pass task ids"):
        encoder(obs)
    with pytest.raises(ValueError, match="task ids must have shape \\(B,\\) = \\(2,\\)"):
        encoder(obs, None, torch.tensor([0]))
    with pytest.raises(ValueError, match="single-task but task ids were given"):
        StateObservations(OBS_DIM)(obs, None, torch.tensor([0, 1]))


def test_a_single_task_encoder_has_no_parameters():
    assert isinstance(build_observation_encoder(OBS_DIM, None), StateObservations)
    assert list(build_observation_encoder(OBS_DIM, None).parameters()) == []
    assert _context(0).feature_dim == OBS_DIM and _context(2).feature_dim == OBS_DIM + 3


@pytest.mark.parametrize("family", sorted(TINY_SECTIONS))
def test_every_family_is_conditioned_on_the_task_and_its_checkpoint_keeps_the_tasks(family, tmp_path):
    torch.manual_seed(0)
    policy = build_policy(family, TINY_SECTIONS[family], _context(2))
    assert policy.num_tasks == 2 and policy.tasks.names == ("task0", "task1")
    with torch.no_grad():  # an untrained embedding: spread the rows so that the tasks differ clearly
        policy.observation_encoder.task_embedding.weight.copy_(torch.tensor([[3.0, -3.0, 3.0], [-3.0, 3.0, -3.0]]))
    obs = np.zeros((1, OBS_STEPS, OBS_DIM), dtype=np.float32)
    features = [policy.observation_features(obs, OBS_STEPS, task_index=task) for task in (0, 1)]
    assert not torch.equal(features[0], features[1])
    policy.select_task("task1")
    selected = policy.observation_features(obs, OBS_STEPS)
    # Task 1's own statistics (task 0's shifted by one) and its embedding row.
    torch.testing.assert_close(selected[..., OBS_DIM:], features[1][..., OBS_DIM:])
    torch.testing.assert_close(selected[..., :OBS_DIM], features[1][..., :OBS_DIM] - 1.0)
    policy.save(tmp_path / "policy.pt")
    loaded = load_policy(tmp_path / "policy.pt")
    assert loaded.tasks.names == ("task0", "task1") and loaded.tasks.selected == "task1"
    torch.testing.assert_close(loaded.observation_features(obs, OBS_STEPS), selected)
    with pytest.raises(ValueError, match="trained on tasks \\['task0', 'task1'\\], not on 'square'"):
        loaded.select_task("square")


@pytest.mark.parametrize("family", sorted(TINY_SECTIONS))
def test_every_family_pads_a_narrower_tasks_own_observations_and_keeps_the_widths(family, tmp_path):
    widths = {"lift": (1, 1), "can": (1, 2)}  # Lift's second key is one feature narrower than Can's
    torch.manual_seed(0)
    policy = build_policy(family, TINY_SECTIONS[family], _context(2, widths))
    own = np.random.default_rng(0).uniform(-1, 1, size=(2, OBS_STEPS, 2)).astype(np.float32)
    padded = np.concatenate([own, np.zeros((2, OBS_STEPS, 1), dtype=np.float32)], axis=-1)
    torch.testing.assert_close(
        policy.observation_features(own, OBS_STEPS), policy.observation_features(padded, OBS_STEPS)
    )
    policy.save(tmp_path / "policy.pt")
    loaded = load_policy(tmp_path / "policy.pt")
    assert loaded.tasks.obs_widths == widths
    torch.testing.assert_close(loaded.observation_features(own, OBS_STEPS), policy.observation_features(own, OBS_STEPS))
    loaded.select_task("can")
    with pytest.raises(ValueError, match=r"obs must have shape \(B, To, Do\) = \(B, 2, 3\), got \(2, 2, 2\)"):
        loaded.observation_features(own, OBS_STEPS)


def test_task_records_are_checked():
    normalizer = MinMaxNormalizer(np.zeros(2), np.ones(2))
    with pytest.raises(ValueError, match="at least two distinct tasks"):
        PolicyTasks(("lift",), {"lift": normalizer}, {"lift": normalizer})
    wide = MinMaxNormalizer(np.zeros(3), np.ones(3))
    with pytest.raises(ValueError, match="obs statistics of the tasks differ in width"):
        PolicyTasks(("lift", "can"), {"lift": normalizer, "can": wide}, {"lift": normalizer, "can": normalizer})
    with pytest.raises(ValueError, match="statistics must be those of the selected task 'task0'"):
        PolicyContext(
            obs_normalizer=wide,
            action_normalizer=normalizer,
            obs_steps=OBS_STEPS,
            action_horizon=8,
            tasks=tiny_tasks(2, normalizer, normalizer),
        )


def test_padded_tasks_round_trip_and_widths_must_pad_to_the_statistics():
    widths = {"lift": (1, 1), "can": (1, 2)}
    tasks = tiny_tasks(
        2, MinMaxNormalizer(np.zeros(3), np.ones(3)), MinMaxNormalizer(np.zeros(2), np.ones(2)), ("lift", "can"), widths
    )
    again = PolicyTasks.from_dict(json.loads(json.dumps(tasks.to_dict())))
    assert again.obs_widths == widths and again.names == tasks.names
    assert again.padding().input_dim == 2 and not again.with_selected("can").padding().pads
    np.testing.assert_array_equal(again.padding().pad(np.ones((1, 2))), [[1.0, 1.0, 0.0]])
    with pytest.raises(ValueError, match="pad to 4 features, the obs statistics have 3"):
        PolicyTasks(
            tasks.names, tasks.obs_normalizers, tasks.action_normalizers, obs_widths={"lift": (1, 1), "can": (2, 2)}
        )
    with pytest.raises(ValueError, match=r"obs widths are for tasks \['lift'\], not \['lift', 'can'\]"):
        PolicyTasks(tasks.names, tasks.obs_normalizers, tasks.action_normalizers, obs_widths={"lift": (1, 2)})


def test_a_diffusion_policy_trains_its_task_embedding_and_the_loop_checks_the_task_ids(tmp_path):
    from carp.config import TrainingConfig
    from carp.policies.registry import train_policy
    from carp.training.loop import PolicyTrainingData

    context = _context(2)
    generator = torch.Generator().manual_seed(0)
    obs = torch.rand(8, OBS_STEPS, OBS_DIM, generator=generator) * 2 - 1
    actions = torch.rand(8, context.action_horizon, 2, generator=generator) * 2 - 1
    training = TrainingConfig(epochs=2, batch_size=4)
    section = TINY_SECTIONS["diffusion_unet"]
    with pytest.raises(ValueError, match="needs task_ids of shape \\(N,\\) = \\(8,\\)"):
        train_policy("diffusion_unet", section, training, context, PolicyTrainingData(obs, actions), tmp_path / "a")
    torch.manual_seed(0)
    initial = build_policy("diffusion_unet", section, context).observation_encoder.task_embedding.weight.clone()
    data = PolicyTrainingData(obs, actions, torch.arange(8) % 2)
    policy = train_policy("diffusion_unet", section, training, context, data, tmp_path / "b")
    assert not torch.equal(policy.observation_encoder.task_embedding.weight, initial)
