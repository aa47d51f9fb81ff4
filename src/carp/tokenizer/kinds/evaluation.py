"""Held-out rate and distortion of a fitted kind in the ``train_tokenizer`` stage's metric keys, and its figure.

The keys share names with ``carp_msvq``'s metrics where they mean the same (``rmse_percent_range/<dimension>`` and
``/mean``, per task ``task/<task>/...``), so `carp.tokenizer.evaluation.summary_line` and the report read both; the
rest come from `carp.tokenizer.rate_distortion`: tokens per chunk, bits per chunk, token entropy, vocabulary and the
share of decodings that had to be repaired. Encode and decode times are returned apart: they vary from run to run
and stay out of the stage's metrics file.
"""

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from carp.data.normalizer import MinMaxNormalizer
from carp.tokenizer.evaluation import dimension_names
from carp.tokenizer.kinds.base import ActionTokenizer
from carp.tokenizer.plots import plot_reconstruction
from carp.tokenizer.rate_distortion import RateDistortion, measure_rate_distortion


def round_trip_trajectory(tokenizer: ActionTokenizer, actions: torch.Tensor) -> torch.Tensor:
    """A whole normalized trajectory (T, A) through encode and decode in consecutive chunks of H, (T, A).

    The last chunk is padded by repeating the final step, as the replay buffer pads windows.
    """
    horizon, steps = tokenizer.action_horizon, actions.shape[0]
    num_chunks = -(-steps // horizon)
    padding = actions[-1:].expand(num_chunks * horizon - steps, -1)
    chunks = torch.cat([actions, padding]).reshape(num_chunks, horizon, -1).float()  # (chunks, H, A)
    return tokenizer.decode(tokenizer.encode(chunks)).actions.reshape(num_chunks * horizon, -1)[:steps]


def _errors(measured: RateDistortion, names: Sequence[str], prefix: str = "") -> dict[str, float]:
    errors = {f"{prefix}rmse_percent_range/{name}": value for name, value in zip(names, measured.rmse_percent_range)}
    errors[f"{prefix}rmse_percent_range/mean"] = measured.rmse_percent_mean
    return errors


def evaluate_kind(
    tokenizer: ActionTokenizer,
    held_out_windows: Mapping[str, np.ndarray],
    normalizers: Mapping[str, MinMaxNormalizer],
    figure_episode: tuple[str, np.ndarray],
    figure_path: Path,
    names: Sequence[str] = (),
) -> tuple[dict[str, float], dict[str, float]]:
    """Rate and distortion on held-out windows of one or more tasks, and a figure of one whole held-out episode.

    Args:
        tokenizer: a fitted tokenizer of any kind.
        held_out_windows: task -> (N_task, H, A) raw action windows, each normalized with its task's statistics.
        normalizers: task -> the statistics that task's actions are normalized with.
        figure_episode: (task, (T, A) raw actions of one of its episodes) for the figure.
        figure_path: PNG written here.
        names: the A dimensions' names (the action format's); empty gives ``dim0, dim1, ...``.

    Returns:
        The metrics (deterministic for a fitted tokenizer) and the encode and decode times in ms per chunk.
    """
    names = dimension_names(tokenizer.action_dim, names)
    windows = {
        task: torch.as_tensor(normalizers[task].normalize(raw.astype(np.float64)), dtype=torch.float32)
        for task, raw in held_out_windows.items()
    }
    measured = measure_rate_distortion(tokenizer, torch.cat(list(windows.values())))
    metrics = {
        **_errors(measured, names),
        "vocabulary_size": float(measured.vocabulary_size),
        "tokens_per_chunk/mean": measured.tokens_mean,
        "tokens_per_chunk/p95": measured.tokens_p95,
        "bits_per_chunk": measured.bits_per_chunk,
        "entropy_bits_per_chunk": measured.entropy_bits_per_chunk,
        "invalid_rate": measured.invalid_rate,
    }
    if len(windows) > 1:
        for task, task_windows in windows.items():
            metrics.update(_errors(measure_rate_distortion(tokenizer, task_windows), names, f"task/{task}/"))
    task, episode_actions = figure_episode
    normalizer = normalizers[task]
    normalized = torch.as_tensor(normalizer.normalize(episode_actions.astype(np.float64)), dtype=torch.float32)
    reconstructed = normalizer.unnormalize(round_trip_trajectory(tokenizer, normalized).double().numpy())
    plot_reconstruction(episode_actions, reconstructed, figure_path, names)
    return metrics, {"encode_ms": measured.encode_ms, "decode_ms": measured.decode_ms}
