import logging
import math

import pytest
import torch

from carp.config import ConfigError
from carp.policies.carp.sampling import generate_chunk
from carp.policies.carp.trainer import compute_token_targets
from carp.training.loop import CHECKPOINT_NAME, NonFiniteLossError, PolicyTrainingData
from tests.policies.carp.factories import OBS_DIM, OBS_STEPS, tiny_tokenizer, train_carp, trainer_settings

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
    settings = dict(
        epochs=60, batch_size=6, learning_rate=1e-2, weight_decay=0.0, warmup_steps=10, width=32, device="cpu"
    )
    policy = train_carp(tokenizer, data, settings, tmp_path, lambda epoch, metrics: history.append(metrics))
    assert history[0]["loss"] > 1.5  # ~ log(8) at the start
    assert history[-1]["loss"] < 0.05
    losses = [metrics["loss"] for metrics in history]
    assert all(later < earlier for earlier, later in zip(losses[:10], losses[1:11], strict=True))
    assert history[-1]["token_accuracy"] == 1.0
    with torch.inference_mode():
        chunk = generate_chunk(policy.transformer, tokenizer, data.obs)
    assert torch.equal(tokenizer.ids_to_sequence(chunk.token_ids), targets.token_sequence)


# Per-epoch metrics and final weight sums of this setup as CARP's dedicated trainer computed them before CARP moved
# onto the shared loop; any change of seeding, data order, dropout draws, parameter groups, AdamW, schedule, EMA, loss
# or accuracy bookkeeping moves them.
FORMER_TRAINER_SETTINGS = dict(
    epochs=4, batch_size=4, learning_rate=3e-3, weight_decay=0.05, warmup_steps=2, dropout=0.1, use_ema=True,
    ema_decay=0.9, checkpoint_every=2, precision="float32", device="cpu",
)  # fmt: skip
FORMER_TRAINER_LOSSES = [2.0698166847229005, 1.9403057098388672, 1.8212637186050415, 1.7625346899032592]
FORMER_TRAINER_ACCURACIES = {
    "token_accuracy": [0.25, 5 / 6, 5 / 6, 5 / 6],
    "token_accuracy_scale_1": [0.2, 0.95, 0.95, 0.95],
    "token_accuracy_scale_2": [0.275, 0.775, 0.775, 0.775],
}
FORMER_TRAINER_WEIGHT_SUM, FORMER_TRAINER_WEIGHT_ABS_SUM = -2.550896014538621, 81.61310652917595


def test_training_repeats_the_former_dedicated_trainer(tmp_path):
    history = []
    policy = train_carp(tiny_tokenizer(), _data(10), FORMER_TRAINER_SETTINGS, tmp_path, lambda e, m: history.append(m))
    assert [metrics["loss"] for metrics in history] == pytest.approx(FORMER_TRAINER_LOSSES, rel=1e-5)
    for name, expected in FORMER_TRAINER_ACCURACIES.items():
        assert [metrics[name] for metrics in history] == pytest.approx(expected, abs=1e-12), name
    weights = [value.double() for value in policy.transformer.state_dict().values() if value.is_floating_point()]
    assert sum(float(value.sum()) for value in weights) == pytest.approx(FORMER_TRAINER_WEIGHT_SUM, rel=1e-4)
    assert sum(float(value.abs().sum()) for value in weights) == pytest.approx(FORMER_TRAINER_WEIGHT_ABS_SUM, rel=1e-5)


def test_metrics_and_learning_rate_schedule(tmp_path):
    history = []
    train_carp(tiny_tokenizer(), _data(16), SETTINGS, tmp_path, lambda e, m: history.append((e, m)))
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
    tokenizer, data = tiny_tokenizer(), _data(10)
    settings = dict(**(SETTINGS | {"use_ema": True, "ema_decay": 0.9}))
    uninterrupted_losses = []
    uninterrupted = _weights(
        train_carp(tokenizer, data, settings, tmp_path / "full", lambda e, m: uninterrupted_losses.append(m["loss"]))
    )

    def interrupt(epoch: int, metrics: dict) -> None:
        if epoch == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train_carp(tokenizer, data, settings, tmp_path / "resumed", interrupt)
    assert (tmp_path / "resumed" / CHECKPOINT_NAME).exists()
    reported = []
    resumed = train_carp(tokenizer, data, settings, tmp_path / "resumed", lambda e, m: reported.append((e, m)))
    # The two epochs of the saved state are reported again (so a resumed run's history is whole), then two trained.
    assert [epoch for epoch, _ in reported] == [0, 1, 2, 3]
    assert [metrics["loss"] for _, metrics in reported] == uninterrupted_losses
    for name, value in _weights(resumed).items():
        assert torch.equal(value, uninterrupted[name]), name
    # A finished run is not repeated: the final state is loaded as is and its stored epochs are reported unchanged
    # (timings included, which a second training could not reproduce).
    replayed = []
    finished = train_carp(tokenizer, data, settings, tmp_path / "resumed", lambda e, m: replayed.append((e, m)))
    assert replayed == reported
    for name, value in _weights(finished).items():
        assert torch.equal(value, uninterrupted[name]), name


def test_ema_returns_averaged_weights(tmp_path):
    tokenizer, data = tiny_tokenizer(), _data(10)
    plain = _weights(train_carp(tokenizer, data, SETTINGS, tmp_path / "plain"))
    settings = dict(**(SETTINGS | {"use_ema": True, "ema_decay": 0.5}))
    policy = train_carp(tokenizer, data, settings, tmp_path / "ema")
    averaged = _weights(policy)
    name = "transformer.blocks.0.feed_forward.expand.weight"
    assert not torch.equal(plain[name], averaged[name])
    assert (plain[name] - averaged[name]).abs().max() < 0.05
    # The frozen tokenizer is unchanged, and the constant index buffers are not averaged.
    assert all(torch.equal(value, plain[name]) for name, value in averaged.items() if name.startswith("tokenizer."))
    transformer = policy.transformer
    assert torch.equal(transformer.level_ids, transformer.layout.level_ids())
    assert torch.equal(transformer.attention_mask, transformer.layout.attention_mask())


def test_checkpoint_of_another_setup_is_ignored(tmp_path, caplog):
    tokenizer, data = tiny_tokenizer(), _data(8)
    train_carp(tokenizer, data, SETTINGS, tmp_path)
    epochs = []
    with caplog.at_level(logging.WARNING):
        train_carp(tokenizer, _data(8, seed=1), SETTINGS, tmp_path, lambda e, m: epochs.append(e))
    assert epochs == [0, 1, 2, 3]
    assert "written for another setup (different data_sha256)" in caplog.text
    # Another tokenizer with the same windows is another setup too: its tokens are other targets.
    with caplog.at_level(logging.WARNING):
        train_carp(tiny_tokenizer(seed=1), _data(8, seed=1), SETTINGS, tmp_path, lambda e, m: epochs.append(e))
    assert epochs == [0, 1, 2, 3] * 2
    assert "written for another setup (different identity)" in caplog.text


def test_a_truncated_state_is_discarded_and_training_starts_over(tmp_path, caplog):
    tokenizer, data = tiny_tokenizer(), _data(8)
    fresh = _weights(train_carp(tokenizer, data, SETTINGS, tmp_path / "fresh"))
    train_carp(tokenizer, data, SETTINGS, tmp_path / "damaged")
    state = tmp_path / "damaged" / CHECKPOINT_NAME
    state.write_bytes(state.read_bytes()[:100])
    epochs = []
    with caplog.at_level(logging.WARNING):
        retrained = train_carp(tokenizer, data, SETTINGS, tmp_path / "damaged", lambda e, m: epochs.append(e))
    assert epochs == [0, 1, 2, 3]
    assert f"discarding training state {state}: not a readable checkpoint" in caplog.text
    for name, value in _weights(retrained).items():
        assert torch.equal(value, fresh[name]), name


def test_non_finite_loss_names_epoch_and_step(tmp_path):
    data = _data(8)
    data.obs[5] = float("nan")
    settings = dict(epochs=2, batch_size=8, device="cpu")
    with pytest.raises(NonFiniteLossError, match="loss is nan at epoch 1, step 1 of 1"):
        train_carp(tiny_tokenizer(), data, settings, tmp_path)


def test_multi_task_data_needs_task_ids(tmp_path):
    with pytest.raises(ValueError, match="needs task_ids of shape \\(N,\\) = \\(8,\\)"):
        train_carp(tiny_tokenizer(), _data(8), SETTINGS, tmp_path, num_tasks=2)
    with pytest.raises(ValueError, match="task_ids must be in \\[0, 2\\)"):
        train_carp(tiny_tokenizer(), _data(8, task_ids=torch.full((8,), 2)), SETTINGS, tmp_path, num_tasks=2)
    with pytest.raises(ValueError, match="task_ids were given but the policy is single-task"):
        train_carp(tiny_tokenizer(), _data(8, task_ids=torch.arange(8) % 2), SETTINGS, tmp_path)
    history = []
    data = _data(8, task_ids=torch.arange(8) % 2)
    policy = train_carp(tiny_tokenizer(), data, SETTINGS, tmp_path, lambda e, m: history.append(m), num_tasks=2)
    assert len(history) == 4
    # The task embedding is trained with the network.
    assert policy.observation_encoder.task_embedding.weight.requires_grad


def test_windows_of_another_shape_are_refused(tmp_path):
    data = _data(4)
    with pytest.raises(ValueError, match="actions must have shape \\(N, H, A\\) = \\(4, 8, 2\\), got \\(4, 7, 2\\)"):
        train_carp(tiny_tokenizer(), PolicyTrainingData(data.obs, data.actions[:, :7]), SETTINGS, tmp_path)


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
