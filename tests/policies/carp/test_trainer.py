import logging
import math

import pytest
import torch

from carp.config import ConfigError
from carp.policies.carp.sampling import generate_chunk
from carp.policies.carp.trainer import CHECKPOINT_NAME, compute_token_targets
from carp.training.loop import NonFiniteLossError, PolicyTrainingData
from tests.policies.carp.factories import (
    OBS_DIM,
    OBS_STEPS,
    tiny_policy_spec,
    tiny_tokenizer,
    train_transformer,
    trainer_settings,
)

SETTINGS = dict(
    epochs=4, batch_size=4, learning_rate=3e-3, weight_decay=0.0, warmup_steps=2, checkpoint_every=2, device="cpu"
)


def _data(count: int, seed: int = 0, task_ids: torch.Tensor | None = None) -> PolicyTrainingData:
    generator = torch.Generator().manual_seed(seed)
    obs = torch.rand(count, OBS_STEPS, OBS_DIM, generator=generator) * 2 - 1
    time = torch.linspace(0, 1, 8)[None, :, None]
    frequency = torch.rand(count, 1, 2, generator=generator) * 3
    actions = torch.sin(2 * math.pi * frequency * time + torch.rand(count, 1, 2, generator=generator) * 6)
    return PolicyTrainingData(obs, actions, task_ids)


def _weights(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {name: value.clone() for name, value in module.state_dict().items()}


def test_overfits_a_handful_of_windows_and_reproduces_their_tokens(tmp_path):
    tokenizer = tiny_tokenizer()
    data = _data(6)
    targets = compute_token_targets(tokenizer, data.actions)
    assert targets.token_sequence.unique(dim=0).shape[0] >= 4  # several different token sequences to memorize
    history = []
    settings = dict(epochs=60, batch_size=6, learning_rate=1e-2, weight_decay=0.0, warmup_steps=10, device="cpu")
    transformer = train_transformer(
        tiny_policy_spec(width=32), tokenizer, data, settings, tmp_path, lambda epoch, metrics: history.append(metrics)
    )
    assert history[0]["loss"] > 1.5  # ~ log(8) at the start
    assert history[-1]["loss"] < 0.05
    assert history[-1]["token_accuracy"] == 1.0
    with torch.inference_mode():
        chunk = generate_chunk(transformer, tokenizer, data.obs)
    assert torch.equal(tokenizer.ids_to_sequence(chunk.token_ids), targets.token_sequence)


def test_metrics_and_learning_rate_schedule(tmp_path):
    history = []
    train_transformer(
        tiny_policy_spec(), tiny_tokenizer(), _data(16), SETTINGS, tmp_path, lambda e, m: history.append((e, m))
    )
    assert [epoch for epoch, _ in history] == [0, 1, 2, 3]
    metrics = history[0][1]
    assert set(metrics) == {
        "loss",
        "token_accuracy",
        "token_accuracy_scale_1",
        "token_accuracy_scale_2",
        "learning_rate",
        "epoch_seconds",
        "samples_per_second",
    }
    assert all(0.0 <= metrics[key] <= 1.0 for key in metrics if key.startswith("token_accuracy"))
    # 16 steps: 2 warm-up steps to the peak, then cosine decay to 1% of it.
    assert history[0][1]["learning_rate"] < SETTINGS["learning_rate"]
    assert history[-1][1]["learning_rate"] == pytest.approx(0.01 * SETTINGS["learning_rate"], rel=1e-6)


def test_resume_continues_from_the_saved_epoch(tmp_path):
    spec, tokenizer, data = tiny_policy_spec(), tiny_tokenizer(), _data(10)
    settings = dict(**(SETTINGS | {"use_ema": True, "ema_decay": 0.9}))
    uninterrupted_losses = []
    uninterrupted = _weights(
        train_transformer(
            spec, tokenizer, data, settings, tmp_path / "full", lambda e, m: uninterrupted_losses.append(m["loss"])
        )
    )

    def interrupt(epoch: int, metrics: dict) -> None:
        if epoch == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train_transformer(spec, tokenizer, data, settings, tmp_path / "resumed", interrupt)
    assert (tmp_path / "resumed" / CHECKPOINT_NAME).exists()
    reported = []
    resumed = train_transformer(
        spec, tokenizer, data, settings, tmp_path / "resumed", lambda e, m: reported.append((e, m))
    )
    # The two epochs of the saved state are reported again (so a resumed run's history is whole), then two trained.
    assert [epoch for epoch, _ in reported] == [0, 1, 2, 3]
    assert [metrics["loss"] for _, metrics in reported] == uninterrupted_losses
    for name, value in _weights(resumed).items():
        assert torch.equal(value, uninterrupted[name]), name
    # A finished run is not repeated: the final state is loaded as is and its stored epochs are reported unchanged
    # (timings included, which a second training could not reproduce).
    replayed = []
    finished = train_transformer(
        spec, tokenizer, data, settings, tmp_path / "resumed", lambda e, m: replayed.append((e, m))
    )
    assert replayed == reported
    for name, value in _weights(finished).items():
        assert torch.equal(value, uninterrupted[name]), name


def test_ema_returns_averaged_weights(tmp_path):
    spec, tokenizer, data = tiny_policy_spec(), tiny_tokenizer(), _data(10)
    plain = _weights(train_transformer(spec, tokenizer, data, SETTINGS, tmp_path / "plain"))
    settings = dict(**(SETTINGS | {"use_ema": True, "ema_decay": 0.5}))
    transformer = train_transformer(spec, tokenizer, data, settings, tmp_path / "ema")
    averaged = _weights(transformer)
    name = "blocks.0.feed_forward.expand.weight"
    assert not torch.equal(plain[name], averaged[name])
    assert (plain[name] - averaged[name]).abs().max() < 0.05
    # The constant index buffers are not averaged.
    assert torch.equal(transformer.level_ids, transformer.layout.level_ids())
    assert torch.equal(transformer.attention_mask, transformer.layout.attention_mask())


def test_checkpoint_of_another_setup_is_ignored(tmp_path, caplog):
    spec, tokenizer, data = tiny_policy_spec(), tiny_tokenizer(), _data(8)
    train_transformer(spec, tokenizer, data, SETTINGS, tmp_path)
    epochs = []
    with caplog.at_level(logging.WARNING):
        train_transformer(spec, tokenizer, _data(8, seed=1), SETTINGS, tmp_path, lambda e, m: epochs.append(e))
    assert epochs == [0, 1, 2, 3]
    assert "written for another setup (different data_and_tokenizer_sha256)" in caplog.text


def test_a_truncated_state_is_discarded_and_training_starts_over(tmp_path, caplog):
    spec, tokenizer, data = tiny_policy_spec(), tiny_tokenizer(), _data(8)
    fresh = _weights(train_transformer(spec, tokenizer, data, SETTINGS, tmp_path / "fresh"))
    train_transformer(spec, tokenizer, data, SETTINGS, tmp_path / "damaged")
    state = tmp_path / "damaged" / CHECKPOINT_NAME
    state.write_bytes(state.read_bytes()[:100])
    epochs = []
    with caplog.at_level(logging.WARNING):
        retrained = train_transformer(
            spec, tokenizer, data, SETTINGS, tmp_path / "damaged", lambda e, m: epochs.append(e)
        )
    assert epochs == [0, 1, 2, 3]
    assert f"discarding training state {state}: not a readable checkpoint" in caplog.text
    for name, value in _weights(retrained).items():
        assert torch.equal(value, fresh[name]), name


def test_non_finite_loss_names_epoch_and_step(tmp_path):
    data = _data(8)
    data.obs[5] = float("nan")
    settings = dict(epochs=2, batch_size=8, device="cpu")
    with pytest.raises(NonFiniteLossError, match="loss is nan at epoch 1, step 1 of 1"):
        train_transformer(tiny_policy_spec(), tiny_tokenizer(), data, settings, tmp_path)


def test_multi_task_data_needs_task_ids(tmp_path):
    spec = tiny_policy_spec(num_tasks=2)
    with pytest.raises(ValueError, match="needs task_ids of shape \\(N,\\) = \\(8,\\)"):
        train_transformer(spec, tiny_tokenizer(), _data(8), SETTINGS, tmp_path)
    with pytest.raises(ValueError, match="task_ids must be in \\[0, 2\\)"):
        train_transformer(spec, tiny_tokenizer(), _data(8, task_ids=torch.full((8,), 2)), SETTINGS, tmp_path)
    history = []
    data = _data(8, task_ids=torch.arange(8) % 2)
    train_transformer(spec, tiny_tokenizer(), data, SETTINGS, tmp_path, lambda e, m: history.append(m))
    assert len(history) == 4


def test_spec_must_match_tokenizer(tmp_path):
    with pytest.raises(ValueError, match="scales: policy \\(1, 2, 3\\) vs tokenizer \\(1, 2\\)"):
        train_transformer(tiny_policy_spec(scales=(1, 2, 3)), tiny_tokenizer(), _data(4), SETTINGS, tmp_path)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"epochs": 0}, "training.epochs=0: must be >= 1"),
        ({"warmup_steps": -1}, "carp.warmup_steps=-1: must be an integer >= 0"),
        ({"learning_rate": 0.0}, "carp.learning_rate=0.0: must be > 0"),
        ({"ema_decay": 1.0}, "carp.ema_decay=1.0: must be in \\(0, 1\\)"),
    ],
)
def test_invalid_settings_are_rejected(overrides, message):
    with pytest.raises(ConfigError, match=message):
        trainer_settings(**overrides)
