"""The two block-causal attention kernels agree, `auto` keeps the faster by its margin, and a run's choice sticks."""

import logging
import math
from types import SimpleNamespace

import pytest
import torch

from carp.config import ConfigError
from carp.policies.carp import attention, trainer
from carp.policies.carp.attention import (
    BLOCKWISE_MARGIN,
    BlockCausalPattern,
    faster_kernel,
    pattern_attention,
    time_interleaved,
)
from carp.policies.carp.config import CarpConfig
from carp.policies.carp.layout import TokenLayout
from carp.policies.registry import load_policy
from carp.training.loop import CHECKPOINT_NAME, PolicyTrainingData
from tests.policies.carp.factories import (
    OBS_DIM,
    OBS_STEPS,
    scrambled_transformer,
    tiny_policy_spec,
    tiny_tokenizer,
    train_carp,
)


def _pattern(layout: TokenLayout, kernel: str) -> BlockCausalPattern:
    return BlockCausalPattern(layout.attention_mask(), tuple(end for _, end in layout.scale_bounds), kernel)


@pytest.mark.parametrize(("action_dim", "scales"), [(10, (1, 2, 3, 4)), (3, (1, 2, 4))])
def test_blockwise_attention_matches_the_masked_kernel_forward_and_backward(action_dim, scales):
    layout = TokenLayout(action_dim, scales)
    generator = torch.Generator().manual_seed(0)
    # Views of a (B, N, Nh, d) tensor, as the transformer passes them.
    inputs = [
        torch.randn(3, layout.sequence_length, 4, 8, generator=generator).transpose(1, 2).requires_grad_()
        for _ in range(3)
    ]
    upstream = torch.randn(3, 4, layout.sequence_length, 8, generator=generator)
    results = {}
    for kernel in ("masked", "blockwise"):
        attended = pattern_attention(*inputs, _pattern(layout, kernel), 0.0)
        results[kernel] = (attended, torch.autograd.grad(attended, inputs, upstream))
    torch.testing.assert_close(results["blockwise"][0], results["masked"][0], rtol=1e-5, atol=1e-6)
    for blockwise, masked in zip(results["blockwise"][1], results["masked"][1], strict=True):
        torch.testing.assert_close(blockwise, masked, rtol=1e-5, atol=1e-5)


def test_the_transformer_trains_with_either_kernel_to_the_same_logits():
    spec = tiny_policy_spec((1, 2, 4))
    transformer = scrambled_transformer(spec)
    obs = torch.randn(5, OBS_STEPS, OBS_DIM)
    teacher = torch.randn(5, spec.sequence_length - spec.action_dim, spec.latent_channels)
    logits = {}
    for kernel in ("masked", "blockwise"):
        transformer.attention_kernel = kernel
        assert transformer.training_pattern().kernel == kernel
        logits[kernel] = transformer(obs, teacher)  # (B, L, V)
    torch.testing.assert_close(logits["blockwise"], logits["masked"], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize(
    ("masked", "blockwise", "expected"),
    [
        (1.0, 0.5, "blockwise"),
        (1.0, BLOCKWISE_MARGIN, "blockwise"),
        (1.0, BLOCKWISE_MARGIN + 0.01, "masked"),  # faster, but within the margin: the fused kernel stays
        (1.0, 1.2, "masked"),
    ],
)
def test_auto_takes_the_blockwise_kernel_only_by_a_clear_margin(masked, blockwise, expected):
    assert faster_kernel({"masked": masked, "blockwise": blockwise}) == expected


def test_kernels_are_timed_in_turn_and_each_gets_its_median(monkeypatch):
    clock, calls = [0.0], []
    durations = {"slow": iter([9.0, 0.03, 0.02, 0.04]), "fast": iter([9.0, 0.001, 0.003, 0.002])}

    def step(name: str) -> None:
        calls.append(name)
        clock[0] += next(durations[name])

    # A clock that only the steps advance, so the medians are exact; the warm-up round is not counted.
    monkeypatch.setattr(attention, "time", SimpleNamespace(perf_counter=lambda: clock[0]))
    seconds = time_interleaved(
        {"slow": lambda: step("slow"), "fast": lambda: step("fast")}, torch.device("cpu"), warmup=1, repeats=3
    )
    assert calls == ["slow", "fast"] * 4
    assert seconds == pytest.approx({"slow": 0.03, "fast": 0.002})


def test_measuring_the_kernels_leaves_the_model_and_the_random_streams_alone():
    transformer = scrambled_transformer(tiny_policy_spec((1, 2))).train()
    before = {name: value.clone() for name, value in transformer.state_dict().items()}
    torch.manual_seed(3)
    seconds = trainer.measure_attention_kernels(transformer, 8, torch.device("cpu"), torch.float32, repeats=2)
    drawn_after = torch.rand(4)
    torch.manual_seed(3)
    assert torch.equal(torch.rand(4), drawn_after)
    assert set(seconds) == {"masked", "blockwise"} and all(value > 0 for value in seconds.values())
    assert all(torch.equal(value, before[name]) for name, value in transformer.state_dict().items())
    assert transformer.attention_kernel == "masked" and all(p.grad is None for p in transformer.parameters())


def test_an_unknown_attention_setting_is_refused():
    with pytest.raises(ConfigError, match=r"carp.attention='flash': must be one of \('auto', 'masked', 'blockwise'\)"):
        CarpConfig(attention="flash")


def _data(count: int = 8) -> PolicyTrainingData:
    generator = torch.Generator().manual_seed(0)
    obs = torch.rand(count, OBS_STEPS, OBS_DIM, generator=generator) * 2 - 1
    time = torch.linspace(0, 1, 8)[None, :, None]
    actions = torch.sin(2 * math.pi * time * torch.rand(count, 1, 2, generator=generator) * 3)
    return PolicyTrainingData(obs, actions)


SETTINGS = dict(epochs=2, batch_size=4, warmup_steps=1, checkpoint_every=1)


def _fake_measurement(monkeypatch, seconds: dict[str, float] | None) -> list[int]:
    """Replace the timing with fixed `seconds` (None: fail if called); returns the batch sizes it was asked for."""
    asked = []

    def measure(transformer, batch_size, device, precision, repeats=None):
        if seconds is None:
            raise AssertionError("the kernels were timed although the choice was already made")
        asked.append(batch_size)
        return seconds

    monkeypatch.setattr(trainer, "measure_attention_kernels", measure)
    return asked


def test_auto_times_a_fresh_run_at_its_batch_size_and_records_the_choice(monkeypatch, tmp_path, caplog):
    asked = _fake_measurement(monkeypatch, {"masked": 2.0, "blockwise": 1.0})
    with caplog.at_level(logging.INFO, logger="carp.policies.carp.trainer"):
        policy = train_carp(tiny_tokenizer(), _data(), SETTINGS | {"attention": "auto"}, tmp_path)
    assert asked == [4]
    assert policy.transformer.attention_kernel == "blockwise"
    assert "attention: auto chose blockwise" in caplog.text
    assert policy.metadata["training_attention"] == "blockwise"
    saved = tmp_path / "policy.pt"
    policy.save(saved)
    assert load_policy(saved).metadata["training_attention"] == "blockwise"


def test_a_resumed_auto_run_keeps_the_kernel_it_started_with(monkeypatch, tmp_path, caplog):
    _fake_measurement(monkeypatch, {"masked": 2.0, "blockwise": 1.0})
    train_carp(tiny_tokenizer(), _data(), SETTINGS | {"attention": "auto"}, tmp_path)
    # The host now times the kernels the other way round; the run continues with its own.
    _fake_measurement(monkeypatch, None)
    with caplog.at_level(logging.INFO):
        policy = train_carp(tiny_tokenizer(), _data(), SETTINGS | {"attention": "auto"}, tmp_path)
    assert "auto keeps blockwise, the kernel of the training state it resumes" in caplog.text
    assert "resuming carp training" in caplog.text
    assert policy.transformer.attention_kernel == "blockwise"


def test_an_explicit_kernel_is_not_timed_and_a_state_of_the_other_kernel_is_not_resumed(monkeypatch, tmp_path, caplog):
    _fake_measurement(monkeypatch, None)
    train_carp(tiny_tokenizer(), _data(), SETTINGS | {"attention": "blockwise"}, tmp_path)
    assert (tmp_path / CHECKPOINT_NAME).exists()
    with caplog.at_level(logging.INFO):
        policy = train_carp(tiny_tokenizer(), _data(), SETTINGS | {"attention": "masked"}, tmp_path)
    assert "written for another setup (different identity)" in caplog.text
    assert policy.transformer.attention_kernel == "masked"
