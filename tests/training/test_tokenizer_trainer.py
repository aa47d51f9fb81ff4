import logging

import pytest
import torch

from carp.config import ConfigError, TokenizerConfig
from carp.tokenizer.artifact import NonFiniteTokenizerError
from carp.tokenizer.metrics import reconstruction_metrics
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.synthetic import min_max_bounds, sliding_windows, synthetic_action_episodes
from carp.training.checkpoint import read_training_state
from carp.training.tokenizer_trainer import (
    CHECKPOINT_NAME,
    _run_metadata,
    augment_windows,
    train_tokenizer,
)

TINY_SPEC = TokenizerSpec(action_dim=2, action_horizon=8, scales=(1, 2), codebook_size=8, latent_channels=4)


def normalized_windows(num_episodes: int, spec: TokenizerSpec, seed: int):
    windows = sliding_windows(synthetic_action_episodes(num_episodes, spec.action_dim, seed=seed), spec.action_horizon)
    low, high = min_max_bounds(windows)
    return torch.as_tensor((windows - low) / (high - low) * 2 - 1)


@pytest.fixture
def windows():
    train = normalized_windows(1, TINY_SPEC, seed=0)[:40]
    valid = normalized_windows(1, TINY_SPEC, seed=1)[:12]
    return train, valid


def tiny_settings(**overrides) -> TokenizerConfig:
    """The `tokenizer` section's training settings for a few quick epochs (train on the cpu)."""
    values = {"epochs": 4, "batch_size": 16, "learning_rate": 1e-2, "seed": 3, "checkpoint_every": 2}
    return TokenizerConfig(**{**values, **overrides})


def parameters_of(tokenizer):
    return {name: value.detach().clone() for name, value in tokenizer.state_dict().items()}


def test_training_reports_metrics_and_saves_a_checkpoint(tmp_path, windows):
    reported = []
    tokenizer = train_tokenizer(
        TINY_SPEC,
        *windows,
        tiny_settings(),
        tmp_path,
        on_epoch_end=lambda epoch, metrics: reported.append((epoch, metrics)),
    )
    assert [epoch for epoch, _ in reported] == [0, 1, 2, 3]
    expected_keys = {
        "train_loss",
        "train_reconstruction_mse",
        "train_vq_loss",
        "valid_reconstruction_mse",
        "learning_rate",
        "restarted_codes",
        "epoch_seconds",
    }
    assert all(set(metrics) == expected_keys for _, metrics in reported)
    assert reported[-1][1]["train_loss"] < reported[0][1]["train_loss"]
    assert not tokenizer.training
    metadata = read_training_state(tmp_path / CHECKPOINT_NAME)["metadata"]
    assert metadata["spec"] == TINY_SPEC.to_dict()


def test_training_is_deterministic(tmp_path, windows):
    first = train_tokenizer(TINY_SPEC, *windows, tiny_settings(epochs=2), tmp_path / "first")
    second = train_tokenizer(TINY_SPEC, *windows, tiny_settings(epochs=2), tmp_path / "second")
    for name, value in parameters_of(first).items():
        assert torch.equal(value, parameters_of(second)[name]), name


class Interrupted(Exception):
    pass


def test_rerun_after_interruption_resumes_and_matches_an_uninterrupted_run(tmp_path, windows):
    uninterrupted_metrics = []
    uninterrupted = train_tokenizer(
        TINY_SPEC,
        *windows,
        tiny_settings(),
        tmp_path / "full",
        on_epoch_end=lambda epoch, metrics: uninterrupted_metrics.append(metrics),
    )

    def crash_after_third_epoch(epoch, metrics):
        if epoch == 2:
            raise Interrupted

    with pytest.raises(Interrupted):
        train_tokenizer(
            TINY_SPEC, *windows, tiny_settings(), tmp_path / "resumed", on_epoch_end=crash_after_third_epoch
        )
    resumed_epochs = []
    resumed_metrics = []

    def record(epoch, metrics):
        resumed_epochs.append(epoch)
        resumed_metrics.append(metrics)

    resumed = train_tokenizer(TINY_SPEC, *windows, tiny_settings(), tmp_path / "resumed", on_epoch_end=record)
    # The checkpoint after epoch 2 is picked up: its two epochs are reported again, then epochs 3 and 4 are trained.
    assert resumed_epochs == [0, 1, 2, 3]
    for name, value in parameters_of(uninterrupted).items():
        assert torch.equal(value, parameters_of(resumed)[name]), name
    assert [m["train_loss"] for m in resumed_metrics] == [m["train_loss"] for m in uninterrupted_metrics]


def test_a_checkpoint_of_another_setup_is_ignored(tmp_path, windows, caplog):
    train_tokenizer(TINY_SPEC, *windows, tiny_settings(epochs=2), tmp_path)
    epochs_run = []
    with caplog.at_level(logging.WARNING):
        train_tokenizer(
            TINY_SPEC,
            *windows,
            tiny_settings(epochs=2, seed=4),
            tmp_path,
            on_epoch_end=lambda epoch, metrics: epochs_run.append(epoch),
        )
    assert epochs_run == [0, 1]
    assert "written for another setup (different settings)" in caplog.text
    assert read_training_state(tmp_path / CHECKPOINT_NAME)["metadata"]["settings"]["seed"] == 4


def test_a_truncated_state_is_discarded_and_training_starts_over(tmp_path, windows, caplog):
    fresh = train_tokenizer(TINY_SPEC, *windows, tiny_settings(epochs=2), tmp_path / "fresh")
    state = tmp_path / "damaged" / CHECKPOINT_NAME
    train_tokenizer(TINY_SPEC, *windows, tiny_settings(epochs=2), state.parent)
    state.write_bytes(state.read_bytes()[: state.stat().st_size // 2])
    epochs_run = []
    with caplog.at_level(logging.WARNING):
        retrained = train_tokenizer(
            TINY_SPEC, *windows, tiny_settings(epochs=2), state.parent, lambda epoch, _: epochs_run.append(epoch)
        )
    assert epochs_run == [0, 1]
    assert f"discarding training state {state}: not a readable checkpoint" in caplog.text
    for name, value in parameters_of(fresh).items():
        assert torch.equal(value, parameters_of(retrained)[name]), name
    assert read_training_state(state)["epoch"] == 2


def test_codebook_starts_from_data_and_restarts_dead_codes(tmp_path, windows):
    reported = []
    train_tokenizer(
        TINY_SPEC,
        *windows,
        tiny_settings(restart_fraction=1.0),
        tmp_path,
        on_epoch_end=lambda epoch, metrics: reported.append(metrics["restarted_codes"]),
    )
    # Some of the 8 codes per dimension go unused in an epoch; while restarts are enabled they are re-seeded.
    assert sum(reported) > 0
    no_restart = []
    train_tokenizer(
        TINY_SPEC,
        *windows,
        tiny_settings(restart_fraction=0.0),
        tmp_path / "none",
        on_epoch_end=lambda epoch, metrics: no_restart.append(metrics["restarted_codes"]),
    )
    assert no_restart == [0.0] * 4


@pytest.mark.parametrize("source", ["nan window", "learning rate 1e10"])
def test_a_diverging_run_is_refused_before_its_state_is_saved(tmp_path, windows, source):
    train, valid = (window.clone() for window in windows)
    settings = tiny_settings(checkpoint_every=1)
    if source == "nan window":
        train[5, 3, 1] = float("nan")
    else:
        settings = tiny_settings(checkpoint_every=1, learning_rate=1e10)
    epochs_run = []
    with pytest.raises(NonFiniteTokenizerError, match=r"tokenizer training epoch 1/4: train_loss=nan: not finite"):
        train_tokenizer(
            TINY_SPEC, train, valid, settings, tmp_path, on_epoch_end=lambda epoch, _: epochs_run.append(epoch)
        )
    assert epochs_run == [] and not (tmp_path / CHECKPOINT_NAME).exists()


def augmentation_input() -> torch.Tensor:
    generator = torch.Generator().manual_seed(5)
    windows = torch.rand(2000, 8, 3, generator=generator) * 1.2 - 0.8  # (N, H, A) spans up to 1.2
    windows[:, :, 2] = 0.3  # a constant dimension can only move
    return windows


def test_augmentation_keeps_windows_in_range_and_transforms_the_requested_share():
    windows = augmentation_input()
    augmented = augment_windows(windows, 0.5, 2.0, torch.Generator().manual_seed(0))
    assert augmented.shape == windows.shape
    assert float(augmented.min()) >= -1.0 - 1e-6 and float(augmented.max()) <= 1.0 + 1e-6
    transformed = (augmented != windows).any(dim=1)  # (N, A)
    assert torch.allclose(transformed.double().mean(dim=0), torch.full((3,), 0.5, dtype=torch.double), atol=0.05)
    untouched = ~transformed[:, None, :].expand_as(windows)
    assert torch.equal(augmented[untouched], windows[untouched])
    span = windows.amax(dim=1) - windows.amin(dim=1)
    factor = (augmented.amax(dim=1) - augmented.amin(dim=1))[:, :2] / span[:, :2]  # amplitude factors, (N, 2)
    assert 0.5 - 1e-4 <= float(factor.min()) and float(factor.max()) <= 2.0 + 1e-4
    assert float(factor.max()) > 1.5 and float(factor.min()) < 0.6, "the factors should fill [1/2, 2]"
    # The constant dimension's level moves anywhere in [-1, 1] but it stays constant.
    assert torch.allclose(augmented[:, :, 2].amax(dim=1), augmented[:, :, 2].amin(dim=1))
    assert float(augmented[:, 0, 2].min()) < -0.9 and float(augmented[:, 0, 2].max()) > 0.9


def test_augmentation_is_reproducible_and_can_be_switched_off():
    windows = augmentation_input()
    first = augment_windows(windows, 0.5, 2.0, torch.Generator().manual_seed(1))
    assert torch.equal(first, augment_windows(windows, 0.5, 2.0, torch.Generator().manual_seed(1)))
    assert torch.equal(augment_windows(windows, 0.0, 2.0, torch.Generator().manual_seed(1)), windows)
    moved = augment_windows(windows, 1.0, 1.0, torch.Generator().manual_seed(1))  # max_scale 1: moves only
    assert torch.allclose(moved - moved[:, :1], windows - windows[:, :1], atol=1e-6)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"epochs": 0}, "tokenizer.epochs=0: must be >= 1"),
        ({"learning_rate": 0.0}, "tokenizer.learning_rate=0.0: must be > 0"),
        ({"warmup_fraction": -0.5}, "tokenizer.warmup_fraction=-0.5: must be in \\[0, 1\\]"),
        ({"restart_fraction": 1.5}, "tokenizer.restart_fraction=1.5: must be in \\[0, 1\\]"),
        ({"augment_probability": -0.1}, "tokenizer.augment_probability=-0.1: must be in \\[0, 1\\]"),
        ({"augment_max_scale": 0.5}, "tokenizer.augment_max_scale=0.5: must be >= 1"),
    ],
)
def test_invalid_settings_are_rejected(overrides, message):
    with pytest.raises(ConfigError, match=message):
        tiny_settings(**overrides)


def test_windows_of_the_wrong_shape_are_rejected(tmp_path):
    with pytest.raises(ValueError, match=r"train_windows must have shape \(N, H, A\) = \(N, 8, 2\)"):
        train_tokenizer(TINY_SPEC, torch.zeros(4, 8, 3), torch.zeros(0, 8, 2), tiny_settings(), tmp_path)


@pytest.mark.slow
def test_default_settings_meet_the_quality_bar_on_synthetic_demos(tmp_path):
    """About 40 pick-and-place-like demos, A = 10: mean RMSE <= 2% of each dimension's range on held-out demos."""
    spec = TokenizerSpec(action_dim=10)
    episodes = synthetic_action_episodes(48, spec.action_dim, seed=0)
    train_raw = sliding_windows(episodes[:40], spec.action_horizon)
    valid_raw = sliding_windows(episodes[40:], spec.action_horizon)
    low, high = (torch.as_tensor(bound) for bound in min_max_bounds(train_raw))

    def normalize(values):
        return (torch.as_tensor(values) - low) / (high - low) * 2 - 1

    # Fewer epochs than the pipeline's default: the bar must hold for a short run too.
    config = TokenizerConfig(epochs=30, checkpoint_every=10)
    tokenizer = train_tokenizer(spec, normalize(train_raw), normalize(valid_raw), config, tmp_path, device="cpu")
    metrics = reconstruction_metrics(tokenizer, normalize(valid_raw), (high - low) / 2)
    assert metrics["rmse_percent_range/mean"] <= 2.0
    assert metrics["usage/all_scales/mean"] > 0.2


def test_the_kind_leaves_a_resumable_state_resumable():
    windows = torch.zeros(4, 8, 2)
    default = _run_metadata(TINY_SPEC, TokenizerConfig(), windows)
    assert _run_metadata(TINY_SPEC, TokenizerConfig(kind="fast"), windows) == default
    # Exactly the training settings: nothing about other kinds reaches the resume check.
    assert set(default["settings"]) == {
        "epochs",
        "batch_size",
        "learning_rate",
        "weight_decay",
        "seed",
        "warmup_fraction",
        "restart_fraction",
        "augment_probability",
        "augment_max_scale",
    }
    assert _run_metadata(TINY_SPEC, TokenizerConfig(epochs=3), windows) != default
