"""VQ-BeT through the registry: train, save, load, resume, the kept VQ-VAE and the freeze schedule."""

import numpy as np
import pytest
import torch

from carp.config import TrainingConfig
from carp.policies.registry import get_family, load_policy, train_policy
from carp.policies.vq_bet import family
from carp.policies.vq_bet.family import AUTOENCODER_NAME
from tests.policies.vq_bet.factories import OBS_DIM, OBS_STEPS, tiny_config, tiny_context, tiny_data

TRAINING = TrainingConfig(epochs=2, batch_size=8, checkpoint_every=1)


def train(directory, **config):
    return train_policy("vq_bet", tiny_config(**config), TRAINING, tiny_context(), tiny_data(), directory)


def raw_obs() -> np.ndarray:
    return np.random.default_rng(1).uniform(-2, 2, size=(4, OBS_STEPS, OBS_DIM)).astype(np.float32)


def test_registered_and_round_trips_through_save_and_load_policy(tmp_path):
    assert get_family("vq_bet").config_class is type(tiny_config())
    policy = train(tmp_path / "state")
    path = tmp_path / "policy.pt"
    policy.save(path)
    loaded = load_policy(path)
    assert loaded.policy_type == "vq_bet" and loaded.metadata == {"task": "pusht"}
    assert loaded.num_parameters == policy.num_parameters
    obs = raw_obs()
    for choice in ("sample", "greedy"):
        policy.configure_inference(code_choice=choice)
        loaded.configure_inference(code_choice=choice)
        expected = policy.predict_action(obs, generator=torch.Generator().manual_seed(3))
        np.testing.assert_array_equal(loaded.predict_action(obs, generator=torch.Generator().manual_seed(3)), expected)


def test_training_is_deterministic_and_keeps_the_fitted_vqvae_for_resuming(tmp_path, monkeypatch):
    first = train(tmp_path / "first")
    assert (tmp_path / "first" / AUTOENCODER_NAME).is_file()
    second = train(tmp_path / "second")
    for name, value in first.state_dict().items():
        assert torch.equal(value, second.state_dict()[name]), name

    def refuse(*args, **kwargs):
        raise AssertionError("the kept VQ-VAE should have been reused")

    monkeypatch.setattr(family, "train_autoencoder", refuse)
    resumed = train(tmp_path / "first")
    for name, value in first.state_dict().items():
        assert torch.equal(value, resumed.state_dict()[name]), name
    with pytest.raises(AssertionError, match="reused"):
        train(tmp_path / "first", vq_training_steps=6)


def test_gpt_and_code_head_freeze_after_half_the_epochs(tmp_path, monkeypatch):
    built = []
    build = family.build
    monkeypatch.setattr(family, "build", lambda *args: built.append(build(*args)) or built[-1])
    states = []

    def remember_weights(epoch, metrics):
        states.append({name: value.clone() for name, value in built[0].transformer.state_dict().items()})

    train_policy(
        "vq_bet",
        tiny_config(),
        TRAINING,
        tiny_context(),
        tiny_data(),
        tmp_path / "state",
        on_epoch_end=remember_weights,
    )
    policy = built[0]
    assert policy.freeze_after_steps == 3 and int(policy.trained_steps) == 6
    after_first, after_second = states
    for name in after_first:
        changed = not torch.equal(after_first[name], after_second[name])
        assert changed == name.startswith("offset_head"), name


class Interrupted(Exception):
    """Stands in for a killed training run."""


def test_a_run_interrupted_in_the_frozen_phase_resumes_to_the_uninterrupted_policy(tmp_path):
    training = TrainingConfig(epochs=4, batch_size=8, checkpoint_every=1)

    def run(directory, on_epoch_end=None):
        return train_policy(
            "vq_bet", tiny_config(), training, tiny_context(), tiny_data(), directory, on_epoch_end=on_epoch_end
        )

    def interrupt_after_third_epoch(epoch, metrics):
        if epoch == 2:
            raise Interrupted

    uninterrupted = run(tmp_path / "uninterrupted")
    with pytest.raises(Interrupted):
        run(tmp_path / "interrupted", interrupt_after_third_epoch)
    resumed = run(tmp_path / "interrupted")
    for name, value in uninterrupted.state_dict().items():
        assert torch.equal(value, resumed.state_dict()[name]), name


def test_an_unreadable_kept_vqvae_is_refitted(tmp_path, caplog):
    directory = tmp_path / "state"
    directory.mkdir()
    (directory / AUTOENCODER_NAME).write_bytes(b"not a checkpoint")
    policy = train(directory)
    assert "refitting the VQ-VAE" in caplog.text
    fresh = train(tmp_path / "fresh")
    assert torch.equal(policy.autoencoder.quantizer.codebooks, fresh.autoencoder.quantizer.codebooks)


def test_the_weight_average_keeps_the_fitted_codebooks(tmp_path):
    policy = train(tmp_path / "state", use_ema=True, ema_decay=0.5)
    kept = torch.load(tmp_path / "state" / AUTOENCODER_NAME, weights_only=True)["state"]
    for name, value in kept.items():
        assert torch.equal(policy.autoencoder.state_dict()[name], value), name
    assert bool(policy.autoencoder.quantizer.initialized)
