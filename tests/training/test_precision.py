import logging

import pytest
import torch
import torch.nn.functional as F

from carp.config import ConfigError
from carp.policies.carp.blocks import _attention
from carp.training import runtime
from carp.training.runtime import autocast_to, resolve_precision
from tests.policies.carp.factories import tiny_tokenizer, train_carp, trainer_settings
from tests.policies.carp.test_trainer import _data

CPU = torch.device("cpu")


@pytest.mark.parametrize("native", [True, False])
def test_auto_precision_follows_native_bfloat16_support(monkeypatch, native):
    monkeypatch.setattr(runtime, "cpu_multiplies_bfloat16", lambda: native)
    assert resolve_precision("auto", CPU) == (torch.bfloat16 if native else torch.float32)
    assert resolve_precision("float32", CPU) == torch.float32
    assert resolve_precision("bfloat16", CPU) == torch.bfloat16


def test_unknown_precision_is_refused():
    with pytest.raises(ValueError, match="precision must be one of .* got 'half'"):
        resolve_precision("half", CPU)
    with pytest.raises(ConfigError, match="training.precision='fp16': must be one of"):
        trainer_settings(precision="fp16")


def test_cpu_attention_stays_float32_under_bfloat16_autocast():
    generator = torch.Generator().manual_seed(0)
    query, key, value = (torch.randn(2, 4, 12, 8, generator=generator) for _ in range(3))
    blocks = torch.repeat_interleave(torch.arange(3), torch.tensor([2, 4, 6]))
    mask = blocks[:, None] >= blocks[None, :]  # (12, 12) block-causal
    with autocast_to(torch.bfloat16, CPU):
        linear_output = F.linear(query, torch.eye(8))
        attended = _attention(query, key, value, mask, 0.0)
        unmasked = _attention(query, key, value, None, 0.0)
    assert linear_output.dtype == torch.bfloat16  # the autocast region is active
    assert attended.dtype == unmasked.dtype == torch.float32
    expected = F.scaled_dot_product_attention(query, key, value, attn_mask=mask)
    torch.testing.assert_close(attended, expected, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(unmasked, F.scaled_dot_product_attention(query, key, value), rtol=1e-6, atol=1e-6)


def _history(tmp_path, precision: str) -> list[dict]:
    settings = dict(
        epochs=6, batch_size=8, learning_rate=3e-3, weight_decay=0.0, warmup_steps=2, device="cpu", precision=precision
    )
    history = []
    train_carp(tiny_tokenizer(), _data(32), settings, tmp_path, lambda e, m: history.append(m))
    return history


def test_bfloat16_training_tracks_float32_training(tmp_path):
    full = _history(tmp_path / "float32", "float32")
    mixed = _history(tmp_path / "bfloat16", "bfloat16")
    full_losses = [metrics["loss"] for metrics in full]
    mixed_losses = [metrics["loss"] for metrics in mixed]
    assert full_losses != mixed_losses  # bfloat16 matmuls did run
    assert mixed_losses[-1] < 0.8 * mixed_losses[0]  # and the model learns
    for full_loss, mixed_loss in zip(full_losses, mixed_losses, strict=True):
        assert mixed_loss == pytest.approx(full_loss, rel=0.01)


def test_a_state_saved_in_another_precision_is_not_resumed(tmp_path, caplog):
    _history(tmp_path, "float32")
    with caplog.at_level(logging.WARNING):
        history = _history(tmp_path, "bfloat16")
    assert len(history) == 6  # trained from the first epoch
    assert "ignoring" in caplog.text
