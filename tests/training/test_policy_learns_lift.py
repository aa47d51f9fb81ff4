"""A short training run on real Lift demos beats an untrained model on held-out windows (a number, not a smoke run)."""

import numpy as np
import pytest
import torch

from carp.data.collect import collect_demonstrations
from carp.data.dataset import load_task_windows
from carp.data.ingest import ingest_demonstrations
from carp.evaluation.offline import held_out_action_errors
from carp.policies.carp.policy import CarpPolicy
from carp.policies.carp.spec import PolicySpec
from carp.policies.carp.transformer import CoarseToFineTransformer
from carp.tokenizer.artifact import TokenizerArtifact
from carp.tokenizer.spec import TokenizerSpec
from carp.training.loop import PolicyTrainingData
from carp.training.tokenizer_trainer import TokenizerTrainingSettings, train_tokenizer
from tests.policies.carp.factories import train_transformer

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
        TokenizerTrainingSettings(epochs=15, batch_size=64, device="cpu"),
        tmp_path / "tokenizer_state",
    ).cpu()
    policy_spec = PolicySpec(
        obs_dim=obs_normalizer.num_features,
        obs_steps=2,
        action_dim=10,
        scales=(1, 2, 4),
        latent_channels=tokenizer_spec.latent_channels,
        codebook_size=64,
        depth=2,
        width=32,
        num_heads=4,
    )
    data = PolicyTrainingData(obs=normalized(obs_normalizer, windows.train_obs), actions=train_actions)
    settings = dict(epochs=40, batch_size=32, learning_rate=2e-3, warmup_steps=10, device="cpu")
    trained = train_transformer(policy_spec, tokenizer, data, settings, tmp_path / "policy_state").cpu()

    torch.manual_seed(0)
    untrained = CoarseToFineTransformer(policy_spec)
    errors = {
        name: held_out_action_errors(
            CarpPolicy(
                TokenizerArtifact.build(tokenizer, {"lift": action_normalizer}, "panda-abs10"),
                transformer,
                obs_normalizer,
                action_normalizer,
            ),
            windows.valid_obs,
            windows.valid_actions,
            obs_steps=2,
            action_steps=8,
        )["valid_executed_action_rmse"]
        for name, transformer in (("trained", trained), ("untrained", untrained))
    }
    # Executed actions of the trained policy are at least twice as close to the held-out demonstrations.
    assert errors["trained"] < 0.5 * errors["untrained"], errors
