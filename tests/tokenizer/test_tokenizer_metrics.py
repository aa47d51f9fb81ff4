import math

import numpy as np
import pytest
import torch

from carp.data.normalizer import MinMaxNormalizer
from carp.tokenizer.evaluation import evaluate_tokenizer, summary_line
from carp.tokenizer.metrics import (
    count_codes,
    perplexity,
    reconstruct,
    reconstruct_trajectory,
    reconstruction_metrics,
)
from carp.tokenizer.task_metrics import TASK_ERROR_METRICS, task_errors


def test_count_codes_histograms_each_dimension_separately():
    token_ids = torch.tensor([[[0, 1], [2, 2]], [[1, 1], [3, 0]]])  # (B=2, A=2, s=2)
    counts = count_codes(token_ids, codebook_size=4)
    assert counts.tolist() == [[1, 3, 0, 0], [1, 0, 2, 1]]


def test_perplexity_counts_effective_codes():
    assert perplexity(torch.tensor([5, 5, 5, 5])).item() == pytest.approx(4.0)
    assert perplexity(torch.tensor([0, 9, 0, 0])).item() == pytest.approx(1.0)
    assert perplexity(torch.tensor([[1, 1, 0, 0], [0, 0, 0, 0]])).tolist() == pytest.approx([2.0, 1.0])


def test_metrics_match_a_manual_computation(tiny_tokenizer, tiny_actions):
    reconstruction, counts = reconstruct(tiny_tokenizer, tiny_actions)
    metrics = reconstruction_metrics(tiny_tokenizer, tiny_actions, torch.ones(2), ["x", "gripper"])
    errors = reconstruction - tiny_actions
    for dimension, name in enumerate(["x", "gripper"]):
        expected_rmse = errors[..., dimension].pow(2).mean().sqrt().item()
        assert metrics[f"rmse/{name}"] == pytest.approx(expected_rmse, rel=1e-5)
        assert metrics[f"mse/{name}"] == pytest.approx(expected_rmse**2, rel=1e-5)
        assert metrics[f"max_error/{name}"] == pytest.approx(errors[..., dimension].abs().max().item(), rel=1e-5)
        # Half range 1 (identity un-normalization): the range is 2, so the percentage is 50 x RMSE.
        assert metrics[f"rmse_percent_range/{name}"] == pytest.approx(50 * expected_rmse, rel=1e-5)
        for scale_index in range(2):
            hit = (counts[scale_index][dimension] > 0).double().mean().item()
            assert metrics[f"usage/scale_{scale_index + 1}/{name}"] == pytest.approx(hit)
        assert 1.0 <= metrics[f"perplexity/{name}"] <= 8.0
    assert metrics["rmse/mean"] == pytest.approx((metrics["rmse/x"] + metrics["rmse/gripper"]) / 2)
    assert metrics["max_error/max"] == pytest.approx(max(metrics["max_error/x"], metrics["max_error/gripper"]))
    assert metrics["reconstruction_mse_normalized"] == pytest.approx(errors.pow(2).mean().item(), rel=1e-5)
    # One window hits at most one code per dimension at scale 1 (s_1 = 1): usage <= 5 windows / 8 codes.
    assert metrics["usage/scale_1/mean"] <= 5 / 8
    assert all(math.isfinite(value) for value in metrics.values())


def test_errors_are_reported_in_original_units(tiny_tokenizer, tiny_actions):
    plain = reconstruction_metrics(tiny_tokenizer, tiny_actions, torch.ones(2))
    scaled = reconstruction_metrics(tiny_tokenizer, tiny_actions, torch.tensor([0.1, 4.0]))
    assert scaled["rmse/dim0"] == pytest.approx(plain["rmse/dim0"] * 0.1, rel=1e-4)
    assert scaled["max_error/dim1"] == pytest.approx(plain["max_error/dim1"] * 4.0, rel=1e-4)
    assert scaled["rmse_percent_range/dim1"] == pytest.approx(plain["rmse_percent_range/dim1"], rel=1e-4)


def test_windows_of_several_tasks_are_measured_against_their_own_ranges(tiny_tokenizer, tiny_actions):
    """Half the windows from a task with 10x the range: original-unit errors scale per window, % of range does not."""
    reconstruction, _ = reconstruct(tiny_tokenizer, tiny_actions)
    errors = reconstruction - tiny_actions  # (N, H, A) normalized
    half_ranges = torch.ones(len(tiny_actions), 1, 2)
    half_ranges[: len(tiny_actions) // 2] = 10.0
    metrics = reconstruction_metrics(tiny_tokenizer, tiny_actions, half_ranges)
    expected = (errors.double() * half_ranges).pow(2).mean(dim=(0, 1)).sqrt()
    assert [metrics["rmse/dim0"], metrics["rmse/dim1"]] == pytest.approx(expected.tolist(), rel=1e-5)
    single = reconstruction_metrics(tiny_tokenizer, tiny_actions, torch.ones(2))
    assert metrics["rmse_percent_range/mean"] == pytest.approx(single["rmse_percent_range/mean"], rel=1e-6)


def test_constant_features_count_as_reconstructed_exactly(tiny_tokenizer, tiny_actions):
    metrics = reconstruction_metrics(tiny_tokenizer, tiny_actions, torch.tensor([1.0, 0.0]))
    assert metrics["rmse/dim1"] == 0.0 and metrics["max_error/dim1"] == 0.0
    assert metrics["rmse_percent_range/dim1"] == 0.0 and metrics["rmse_percent_range/dim0"] > 0.0


def test_metrics_reject_bad_names_and_empty_windows(tiny_tokenizer, tiny_actions):
    with pytest.raises(ValueError, match="expected 2 dimension names, got 1"):
        reconstruction_metrics(tiny_tokenizer, tiny_actions, torch.ones(2), ["x"])
    with pytest.raises(ValueError, match="need at least one window"):
        reconstruction_metrics(tiny_tokenizer, tiny_actions[:0], torch.ones(2))


def test_trajectory_reconstruction_decodes_consecutive_chunks(tiny_tokenizer):
    trajectory = torch.linspace(-1, 1, 20)[:, None].repeat(1, 2)  # (T=20, A=2), not a multiple of H=8
    reconstruction = reconstruct_trajectory(tiny_tokenizer, trajectory)
    assert reconstruction.shape == (20, 2)
    first_chunk, _ = reconstruct(tiny_tokenizer, trajectory[None, 8:16])
    assert torch.allclose(reconstruction[8:16], first_chunk[0], atol=1e-6)
    padded_tail = torch.cat([trajectory[16:], trajectory[-1:].expand(4, 2)])
    last_chunk, _ = reconstruct(tiny_tokenizer, padded_tail[None])
    assert torch.allclose(reconstruction[16:], last_chunk[0, :4], atol=1e-6)


def test_a_tokenizer_measured_on_several_tasks_reports_each_tasks_own_errors(tiny_tokenizer, tiny_actions, tmp_path):
    # Two tasks whose actions span 1x and 10x the range: pooled errors mix them, each task's own are its alone.
    normalizers = {
        "lift": MinMaxNormalizer(np.array([-1.0, -1.0]), np.array([1.0, 1.0])),
        "can": MinMaxNormalizer(np.array([-10.0, -10.0]), np.array([10.0, 10.0])),
    }
    raw = {"lift": tiny_actions[:3].double().numpy(), "can": 10.0 * tiny_actions[3:].double().numpy()}
    figure = ("lift", raw["lift"][0])
    metrics = evaluate_tokenizer(tiny_tokenizer, raw, normalizers, figure, tmp_path / "figure.png")
    alone = {
        task: evaluate_tokenizer(
            tiny_tokenizer, {task: raw[task]}, normalizers, (task, raw[task][0]), tmp_path / "f.png"
        )
        for task in raw
    }
    for task, own in task_errors(metrics).items():
        assert own == pytest.approx(
            {key: value for key, value in alone[task].items() if key.startswith(TASK_ERROR_METRICS)}
        )
    assert set(task_errors(metrics)) == {"lift", "can"}
    assert task_errors(metrics)["can"]["rmse/dim0"] == pytest.approx(
        10 * reconstruction_metrics(tiny_tokenizer, tiny_actions[3:], torch.ones(2))["rmse/dim0"], rel=1e-5
    )
    # One task: nothing per task (it would repeat the pooled figures).
    assert task_errors(alone["lift"]) == {}
    assert "(lift " in summary_line(metrics, ("dim0", "dim1")) and "can " in summary_line(metrics, ("dim0", "dim1"))
