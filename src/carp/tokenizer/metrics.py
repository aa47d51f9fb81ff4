"""Reconstruction quality and codebook health of a trained tokenizer (docs/architecture.md, "Action tokenizer").

Metric keys are flat strings (ready for MLflow) of the form `<metric>/<dimension name>` plus `<metric>/mean`;
scales are numbered from 1 in keys (`usage/scale_1/...` is the coarsest scale).
"""

from collections.abc import Sequence

import torch

from carp.tokenizer.tokenizer import MultiScaleActionTokenizer

METRICS_BATCH_SIZE = 2048


def count_codes(token_ids: torch.Tensor, codebook_size: int) -> torch.Tensor:
    """Histogram of one scale's ids (B, A, s) per dimension, (A, V) long."""
    num_dimensions = token_ids.shape[1]
    offsets = torch.arange(num_dimensions, device=token_ids.device) * codebook_size
    flat = (token_ids + offsets[None, :, None]).reshape(-1)
    return torch.bincount(flat, minlength=num_dimensions * codebook_size).reshape(num_dimensions, codebook_size)


def perplexity(counts: torch.Tensor) -> torch.Tensor:
    """exp(entropy) of code histograms (..., V): the effective number of codes in use, (...)."""
    probabilities = counts.double() / counts.sum(dim=-1, keepdim=True).clamp(min=1)
    entropy = -(probabilities * probabilities.clamp(min=1e-30).log()).sum(dim=-1)
    return entropy.exp()


@torch.no_grad()
def reconstruct(tokenizer: MultiScaleActionTokenizer, windows: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """Encode -> ids -> decode normalized windows (N, H, A) in eval mode.

    Returns:
        Reconstructions (N, H, A) and per-scale code histograms, K tensors (A, V) long.
    """
    was_training = tokenizer.training
    tokenizer.eval()
    spec = tokenizer.spec
    counts = [torch.zeros(spec.action_dim, spec.codebook_size, dtype=torch.long) for _ in spec.scales]
    reconstructions = []
    for batch in torch.split(windows, METRICS_BATCH_SIZE):
        token_ids = tokenizer.encode_to_ids(batch)
        reconstructions.append(tokenizer.decode_ids(token_ids).cpu())
        for scale_index, ids in enumerate(token_ids):
            counts[scale_index] += count_codes(ids, spec.codebook_size).cpu()
    tokenizer.train(was_training)
    return torch.cat(reconstructions), counts


def reconstruction_metrics(
    tokenizer: MultiScaleActionTokenizer,
    windows: torch.Tensor,
    half_ranges: torch.Tensor,
    dimension_names: Sequence[str] | None = None,
) -> dict[str, float]:
    """Per-dimension reconstruction errors in original units and codebook usage on held-out windows.

    Args:
        tokenizer: trained tokenizer.
        windows: (N, H, A) float normalized windows.
        half_ranges: original action units per normalized unit, (A,) for windows of one normalization or (N, 1, A)
            when windows of several tasks each carry their task's statistics (see
            `carp.data.normalizer.MinMaxNormalizer.half_range`; 0 for constant features).
        dimension_names: A names used in the keys (default dim0, dim1, ...).

    Returns:
        For every dimension name n: `rmse/n`, `mse/n`, `max_error/n` (original units), `rmse_percent_range/n`
        (RMSE as % of the dimension's normalization range, each window's error relative to its own task's range),
        `usage/scale_k/n` (fraction of the V codes hit at scale k), `usage/all_scales/n` and `perplexity/n` (over
        all scales); the same keys with n = mean (mean over dimensions), plus `max_error/max` and
        `reconstruction_mse_normalized`.
    """
    spec = tokenizer.spec
    names = list(dimension_names) if dimension_names is not None else [f"dim{d}" for d in range(spec.action_dim)]
    if len(names) != spec.action_dim:
        raise ValueError(f"expected {spec.action_dim} dimension names, got {len(names)}")
    if windows.shape[0] == 0:
        raise ValueError("need at least one window to measure reconstruction")
    windows = windows.to(next(tokenizer.parameters()).device, torch.float32)
    reconstructions, counts = reconstruct(tokenizer, windows)
    windows = windows.cpu()
    half_ranges = torch.as_tensor(half_ranges, dtype=torch.float64)
    normalized_errors = (reconstructions - windows).double()  # (N, H, A)
    errors = normalized_errors * half_ranges  # (N, H, A) original units
    mse = errors.pow(2).mean(dim=(0, 1))  # (A,)
    rmse = mse.sqrt()
    max_error = errors.abs().amax(dim=(0, 1))
    # A normalized error e is e / 2 of the range; constant features (half range 0) reconstruct exactly.
    relative_errors = torch.where(half_ranges > 0, normalized_errors / 2.0, 0.0)

    per_dimension: dict[str, torch.Tensor] = {
        "rmse": rmse,
        "mse": mse,
        "max_error": max_error,
        "rmse_percent_range": 100.0 * relative_errors.pow(2).mean(dim=(0, 1)).sqrt(),
    }
    for scale_index, scale_counts in enumerate(counts):
        per_dimension[f"usage/scale_{scale_index + 1}"] = (scale_counts > 0).double().mean(dim=-1)
    all_counts = torch.stack(counts).sum(dim=0)  # (A, V)
    per_dimension["usage/all_scales"] = (all_counts > 0).double().mean(dim=-1)
    per_dimension["perplexity"] = perplexity(all_counts)

    metrics: dict[str, float] = {}
    for metric, values in per_dimension.items():
        for name, value in zip(names, values.tolist(), strict=True):
            metrics[f"{metric}/{name}"] = float(value)
        metrics[f"{metric}/mean"] = float(values.double().mean())
    metrics["max_error/max"] = float(max_error.max())
    metrics["reconstruction_mse_normalized"] = float((reconstructions - windows).pow(2).mean())
    return metrics


@torch.no_grad()
def reconstruct_trajectory(tokenizer: MultiScaleActionTokenizer, actions: torch.Tensor) -> torch.Tensor:
    """Reconstruct a whole normalized trajectory (T, A) chunk by chunk (non-overlapping windows of H), (T, A).

    The last chunk is padded by repeating the final step, as the replay buffer pads windows.
    """
    horizon = tokenizer.spec.action_horizon
    steps = actions.shape[0]
    num_chunks = -(-steps // horizon)
    padding = actions[-1:].expand(num_chunks * horizon - steps, -1)
    chunks = torch.cat([actions, padding]).reshape(num_chunks, horizon, -1)  # (chunks, H, A)
    reconstruction, _ = reconstruct(tokenizer, chunks.to(next(tokenizer.parameters()).device, torch.float32))
    return reconstruction.reshape(num_chunks * horizon, -1)[:steps]
