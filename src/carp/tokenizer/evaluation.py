"""Held-out quality of a tokenizer in original action units: metrics plus the raw-vs-reconstructed figure."""

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from carp.data.normalizer import MinMaxNormalizer
from carp.tokenizer.metrics import reconstruct_trajectory, reconstruction_metrics
from carp.tokenizer.plots import plot_reconstruction
from carp.tokenizer.task_metrics import TASK_ERROR_METRICS, task_errors
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer


def dimension_names(action_dim: int, names: Sequence[str] = ()) -> tuple[str, ...]:
    """Names of the A action dimensions: ``names`` (an action format's) when given, else ``dim0, dim1, ...``."""
    if names:
        if len(names) != action_dim:
            raise ValueError(f"expected {action_dim} dimension names, got {len(names)}: {list(names)}")
        return tuple(names)
    return tuple(f"dim{index}" for index in range(action_dim))


def evaluate_tokenizer(
    tokenizer: MultiScaleActionTokenizer,
    held_out_windows: Mapping[str, np.ndarray],
    normalizers: Mapping[str, MinMaxNormalizer],
    figure_episode: tuple[str, np.ndarray],
    figure_path: Path,
    names: Sequence[str] = (),
) -> dict[str, float]:
    """Reconstruction metrics on held-out windows of one or more tasks and a figure of one whole held-out episode.

    Each task's windows are normalized with that task's own statistics, as in training (`carp.tokenizer.artifact`).

    Args:
        tokenizer: trained tokenizer (CPU, eval mode).
        held_out_windows: task -> (N_task, H, A) raw action windows.
        normalizers: task -> the statistics that task's actions are normalized with.
        figure_episode: (task, (T, A) raw actions of one of its episodes) for the figure.
        figure_path: PNG written here.
        names: the A dimensions' names in metric keys and subplot titles (the action format's); empty gives
            ``dim0, dim1, ...``.

    Returns:
        The flat metrics of :func:`carp.tokenizer.metrics.reconstruction_metrics` over all tasks' windows; with
        several tasks, each task's own as well, keyed ``task/<task>/<metric>/<dimension>`` for the errors (RMSE, %
        of range, max error), since a shared tokenizer can fit one task's actions much better than another's.
    """
    names = dimension_names(tokenizer.spec.action_dim, names)
    windows, half_ranges = {}, {}
    for task, task_windows in held_out_windows.items():
        normalizer = normalizers[task]
        windows[task] = torch.as_tensor(normalizer.normalize(task_windows.astype(np.float64)), dtype=torch.float32)
        half_ranges[task] = torch.as_tensor(normalizer.half_range()).expand(len(task_windows), 1, -1)
    metrics = reconstruction_metrics(
        tokenizer, torch.cat(list(windows.values())), torch.cat(list(half_ranges.values())), names
    )
    if len(windows) > 1:
        for task in windows:
            own = reconstruction_metrics(tokenizer, windows[task], half_ranges[task], names)
            metrics.update(
                {f"task/{task}/{key}": value for key, value in own.items() if key.startswith(TASK_ERROR_METRICS)}
            )
    task, episode_actions = figure_episode
    normalizer = normalizers[task]
    normalized_episode = torch.as_tensor(normalizer.normalize(episode_actions.astype(np.float64)), dtype=torch.float32)
    reconstructed = normalizer.unnormalize(reconstruct_trajectory(tokenizer, normalized_episode).double().numpy())
    plot_reconstruction(episode_actions, reconstructed, figure_path, names)
    return metrics


def summary_line(metrics: dict[str, float], names: Sequence[str]) -> str:
    """One line summarizing the reconstruction error (mean and worst dimension as % of range), then each task's mean."""
    worst = max(names, key=lambda name: metrics[f"rmse_percent_range/{name}"])
    line = (
        f"mean RMSE {metrics['rmse_percent_range/mean']:.2f}% of range, worst {worst} "
        f"{metrics[f'rmse_percent_range/{worst}']:.2f}%"
    )
    per_task = [f"{task} {own['rmse_percent_range/mean']:.2f}%" for task, own in task_errors(metrics).items()]
    return f"{line} ({', '.join(per_task)})" if per_task else line
