"""The two kernels of CARP's block-causal training attention, and the measurement that picks one (`carp.attention`).

Teacher-forced training attends the queries of scale k to the keys of scales 1..k. Two kernels compute the same
values (to float rounding):

- ``masked``: one `F.scaled_dot_product_attention` call with the dense (L, L) mask. One fused kernel, but it scores
  every query against every key and masks a third of the scores away (scales (1, 2, 3, 4)).
- ``blockwise``: one unmasked product per scale, the queries of scale k against the keys of scales 1..k. It computes
  only the scores that count, in K smaller matmuls.

Which one is faster depends on the CPU's kernels (and on the batch and thread count), and the gap can be large in
either direction, so ``auto`` times training steps with each (`carp.policies.carp.trainer.measure_attention_kernels`)
when a run starts and keeps the faster (:func:`faster_kernel`). Timing the attention call alone does not predict
the step: the call's inputs are views of the fused projection, and the step includes the backward into it.
Inference (kv-cache, no mask) uses neither.
"""

import statistics
import time
from collections.abc import Callable
from typing import NamedTuple

import torch
import torch.nn.functional as F

ATTENTION_KERNELS = ("masked", "blockwise")
MEASURE_WARMUP = 1
MEASURE_REPEATS = 7
BLOCKWISE_MARGIN = 0.90
"""``auto`` takes the blockwise kernel only when its steps take at most this share of the masked kernel's: a short
measurement on a shared host scatters by several percent, and within that the single fused kernel is kept, so that
runs on one host do not flip between kernels by chance."""


class BlockCausalPattern(NamedTuple):
    """The training attention pattern, in the form both kernels read, and which kernel computes it.

    Attributes:
        dense: (L, L) bool, True where the query (row) may attend the key (column).
        block_ends: exclusive end of each scale's tokens along the sequence, ascending, the last equal to L.
        kernel: "masked" or "blockwise".
    """

    dense: torch.Tensor
    block_ends: tuple[int, ...]
    kernel: str = "masked"


def blockwise_attention(
    query: torch.Tensor, key: torch.Tensor, value: torch.Tensor, block_ends: tuple[int, ...], dropout: float
) -> torch.Tensor:
    """Block-causal attention of (B, Nh, L, d) queries, keys and values, one unmasked product per block.

    The queries of block k score the keys of blocks 1..k only, so no score is computed and then masked away.

    Returns:
        (B, Nh, L, d).
    """
    scale = query.shape[-1] ** -0.5
    attended = []
    start = 0
    for end in block_ends:
        scores = torch.matmul(query[:, :, start:end] * scale, key[:, :, :end].transpose(-1, -2))  # (B, Nh, n_k, end)
        weights = torch.softmax(scores, dim=-1)
        if dropout > 0:
            weights = F.dropout(weights, dropout)
        attended.append(torch.matmul(weights, value[:, :, :end]))  # (B, Nh, n_k, d)
        start = end
    return torch.cat(attended, dim=2)  # (B, Nh, L, d)


def pattern_attention(
    query: torch.Tensor, key: torch.Tensor, value: torch.Tensor, pattern: BlockCausalPattern, dropout: float
) -> torch.Tensor:
    """Block-causal attention of (B, Nh, L, d) tensors by `pattern.kernel`; (B, Nh, L, d)."""
    if pattern.kernel == "blockwise":
        return blockwise_attention(query, key, value, pattern.block_ends, dropout)
    return F.scaled_dot_product_attention(query, key, value, attn_mask=pattern.dense, dropout_p=dropout)


def time_interleaved(
    steps: dict[str, Callable[[], None]],
    device: torch.device,
    warmup: int = MEASURE_WARMUP,
    repeats: int = MEASURE_REPEATS,
) -> dict[str, float]:
    """Median seconds of each of `steps` (name -> a call), run in turn `repeats` times after `warmup` untimed rounds.

    Taking the steps in turn lets a drift of the host's speed hit each of them alike.
    """
    for _ in range(warmup):
        for step in steps.values():
            step()
    seconds: dict[str, list[float]] = {name: [] for name in steps}
    for _ in range(repeats):
        for name, step in steps.items():
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            started = time.perf_counter()
            step()
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            seconds[name].append(time.perf_counter() - started)
    return {name: statistics.median(values) for name, values in seconds.items()}


def faster_kernel(seconds: dict[str, float]) -> str:
    """The kernel ``auto`` keeps given each kernel's measured seconds: blockwise only by a clear margin."""
    return "blockwise" if seconds["blockwise"] <= BLOCKWISE_MARGIN * seconds["masked"] else "masked"
