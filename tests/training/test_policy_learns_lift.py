"""A short training run on real Lift demos beats an untrained model on held-out windows (a number, not a smoke run)."""

import numpy as np
import pytest
import torch

from carp.config import TokenizerConfig, TrainingConfig
from carp.data.collect import collect_demonstrations
from carp.data.dataset import load_task_windows
from carp.data.ingest import ingest_demonstrations
from carp.evaluation.offline import held_out_action_errors
from carp.policies.carp.config import CarpConfig
from carp.policies.carp.family import build_policy, train
from carp.policies.context import PolicyContext
from carp.policies.registry import TrainingRun
from carp.tokenizer.artifact import TokenizerArtifact
from carp.tokenizer.spec import TokenizerSpec
from carp.training.loop import PolicyTrainingData
from carp.training.tokenizer_trainer import train_tokenizer

OBS_KEYS = ("object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")


@pytest.mark.slow
def test_short_training_on_lift_beats_an_untrained_policy(tmp_path):
    raw = tmp_path / "lift.hdf5"
    collect_demonstrations("lift", num_demos=8, output_path=raw, seed=700)
    ingest_demonstrations(raw, tmp_path / "processed", OBS_KEYS, valid_fraction=0.25)  # 2 demos held out
    windows = load_task_windows(tmp_path / "processed", horizon=16, obs_steps=2, action_steps=8)
    obs_normalizer, action_normalizer = windows.obs_normalizer, windows.action_normalizer

    def normalized(normalizer, values):
        return torch.as_tensor(normalizer.normalize(values.astype(np.float64)), dtype=torch.float32)

    train_actions = normalized(action_normalizer, windows.train_actions)
    tokenizer_spec = TokenizerSpec(action_dim=10, action_horizon=16, scales=(1, 2, 4), codebook_size=64)
    tokenizer = train_tokenizer(
        tokenizer_spec,
        train_actions,
        normalized(action_normalizer, windows.valid_actions),
        TokenizerConfig(epochs=15, batch_size=64),
        tmp_path / "tokenizer_state",
    ).cpu()
    context = PolicyContext(
        obs_normalizer=obs_normalizer,
        action_normalizer=action_normalizer,
        obs_steps=2,
        action_horizon=16,
        tokenizer_artifact=TokenizerArtifact.build(tokenizer, {"lift": action_normalizer}, "panda-abs10"),
    )
    config = CarpConfig(depth=2, width=32, num_heads=4, learning_rate=2e-3, warmup_steps=10)
    data = PolicyTrainingData(obs=normalized(obs_normalizer, windows.train_obs), actions=train_actions)
    run = TrainingRun(TrainingConfig(epochs=40, batch_size=32), context, data, tmp_path / "policy_state")
    trained = train(config, run).cpu()

    torch.manual_seed(0)
    untrained = build_policy(config, context)
    errors = {
        name: held_out_action_errors(policy, windows.valid_obs, windows.valid_actions, obs_steps=2, action_steps=8)[
            "valid_executed_action_rmse"
        ]
        for name, policy in (("trained", trained), ("untrained", untrained))
    }
    # Executed actions of the trained policy are at least twice as close to the held-out demonstrations.
    assert errors["trained"] < 0.5 * errors["untrained"], errors
