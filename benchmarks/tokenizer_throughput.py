"""Training throughput of the vectorized tokenizer vs a Python loop over A single-dimension tokenizers.

Both variants are the same class (`MultiScaleActionTokenizer`, the loop's with action_dim = 1) and compute the same
math from the same initial weights (the loop's modules are split off the vectorized one with
`carp.tokenizer.per_dimension`): per batch, forward + backward of the summed per-dimension losses and one fused AdamW
step. Throughput is measured over whole epochs of synthetic pick-and-place windows after a short warm-up, and the
median epoch of each variant over `--rounds` epochs is reported, with the ratio of the two (the speed-up of
vectorizing). The header names the CPU's SIMD level as PyTorch dispatches to it (AVX512, AVX2, ...), which the ratio
depends on, as it does on the batch size: vectorizing removes a per-call cost, which a bigger batch spreads over more
windows.

Interleaving (`--block`): on a shared virtual machine the host's speed drifts by 10-50% within a minute, so the two
variants must meet the same host. Each epoch's batches are taken in blocks of `--block` consecutive batches (8 by
default), every block runs through both variants, one after the other with the order alternating from block to
block, and a variant's epoch time is the sum of its timed blocks: a slow spell of the host lands on both within ~2 s.
Blocks rather than single batches because a variant's first step after the other variant's is ~5% slower (caches,
allocator), which in training, where steps of one model follow each other, never happens. `--block 0` runs whole
epochs alternately, where single rounds spread far more.

Device (`--device`): "auto" as the pipeline's `device` param, so CUDA where present; the timer waits for the GPU
at the end of every block.

    .venv/bin/python benchmarks/tokenizer_throughput.py [--threads 1] [--batch-size 64] [--episodes 40] [--rounds 9]
        [--block 8] [--device auto]
"""

import argparse
import statistics
import time
from collections.abc import Callable, Sequence

import torch

from carp.config import TokenizerConfig
from carp.tokenizer.per_dimension import split_into_single_dimension_tokenizers
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.synthetic import min_max_bounds, sliding_windows, synthetic_action_episodes
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer
from carp.training.runtime import resolve_device

WARMUP_STEPS = 3

Step = Callable[[torch.Tensor], None]


def make_windows(num_episodes: int, spec: TokenizerSpec) -> torch.Tensor:
    windows = sliding_windows(synthetic_action_episodes(num_episodes, spec.action_dim, seed=0), spec.action_horizon)
    low, high = min_max_bounds(windows)
    return torch.as_tensor((windows - low) / (high - low) * 2 - 1)


def vectorized_step(tokenizer, optimizer, batch):
    optimizer.zero_grad(set_to_none=True)
    tokenizer(batch).loss.backward()
    optimizer.step()


def loop_step(tokenizers, optimizer, batch):
    optimizer.zero_grad(set_to_none=True)
    for dimension, tokenizer in enumerate(tokenizers):
        tokenizer(batch[:, :, dimension : dimension + 1]).loss.backward()
    optimizer.step()


def shuffled_batches(windows: torch.Tensor, batch_size: int) -> tuple[torch.Tensor, ...]:
    """One epoch's batches, (b, H, A) each, in a fresh random order."""
    return torch.split(windows[torch.randperm(windows.shape[0], device=windows.device)], batch_size)


def timed_block(step: Step, batches: Sequence[torch.Tensor]) -> float:
    started = time.perf_counter()
    for batch in batches:
        step(batch)
    if batches[0].is_cuda:
        torch.cuda.synchronize(batches[0].device)  # kernels are queued: wait for them before reading the clock
    return time.perf_counter() - started


def interleaved_epoch_seconds(steps: dict[str, Step], windows: torch.Tensor, batch_size: int, block: int) -> dict:
    """One epoch of every variant, blocks of `block` batches (0: the whole epoch) in turn; seconds per variant."""
    batches = shuffled_batches(windows, batch_size)
    for step in steps.values():
        timed_block(step, batches[:WARMUP_STEPS])
    block = block or len(batches)
    seconds = dict.fromkeys(steps, 0.0)
    names = list(steps)
    for index, first in enumerate(range(0, len(batches), block)):
        turn = index % len(names)  # alternate who goes first
        for name in names[turn:] + names[:turn]:
            seconds[name] += timed_block(steps[name], batches[first : first + block])
    return seconds


def device_description(device: torch.device) -> str:
    """The device and, on a CPU, the SIMD level PyTorch dispatches to ("cpu AVX512"): the ratio depends on it."""
    if device.type == "cpu":
        return f"cpu {torch.backends.cpu.get_cpu_capability()}"
    return str(device)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--batch-size", type=int, default=TokenizerConfig().batch_size)
    parser.add_argument("--episodes", type=int, default=40, help="synthetic demos (about 118 windows each)")
    parser.add_argument("--rounds", type=int, default=9, help="epochs per variant")
    parser.add_argument("--block", type=int, default=8, help="batches per variant's turn; 0: whole epochs in turn")
    parser.add_argument("--device", default="auto", help='"auto", "cpu", "cuda", ...')
    arguments = parser.parse_args()
    if arguments.rounds < 1:
        parser.error(f"--rounds must be at least 1, got {arguments.rounds}")
    if arguments.block < 0:
        parser.error(f"--block must be 0 (whole epochs) or a positive number of batches, got {arguments.block}")
    try:
        device = resolve_device(arguments.device)
    except RuntimeError:
        parser.error(f'--device must be "auto", "cpu", "cuda" or "cuda:<index>", got {arguments.device!r}')
    if device.type == "cuda" and not torch.cuda.is_available():
        parser.error(f"--device {arguments.device}: CUDA is not available here")
    torch.set_num_threads(arguments.threads)
    torch.manual_seed(0)

    spec = TokenizerSpec(action_dim=10)
    windows = make_windows(arguments.episodes, spec).to(device)
    vectorized = MultiScaleActionTokenizer(spec).to(device).train()
    singles = [single.train() for single in split_into_single_dimension_tokenizers(vectorized)]
    # Both use the trainer's optimizer (fused AdamW), so the comparison isolates the model's forward and backward.
    vectorized_optimizer = torch.optim.AdamW(vectorized.parameters(), lr=1e-3, fused=True)
    loop_optimizer = torch.optim.AdamW([p for single in singles for p in single.parameters()], lr=1e-3, fused=True)

    vectorized_name, loop_name = "vectorized (one module)", f"loop over {spec.action_dim} modules"
    steps: dict[str, Step] = {
        vectorized_name: lambda batch: vectorized_step(vectorized, vectorized_optimizer, batch),
        loop_name: lambda batch: loop_step(singles, loop_optimizer, batch),
    }
    seconds: dict[str, list[float]] = {name: [] for name in steps}
    for _ in range(arguments.rounds):
        for name, value in interleaved_epoch_seconds(steps, windows, arguments.batch_size, arguments.block).items():
            seconds[name].append(value)
    turns = f"{arguments.block} batches" if arguments.block else "whole epochs"
    rates = {name: windows.shape[0] / statistics.median(values) for name, values in seconds.items()}
    speed_ups = {name: rate / rates[loop_name] for name, rate in rates.items()}
    print(
        f"tokenizer training throughput: A={spec.action_dim}, H={spec.action_horizon}, V={spec.codebook_size}, "
        f"batch {arguments.batch_size}, {windows.shape[0]} windows, {device_description(device)}, "
        f"{arguments.threads} thread(s), "
        f"median of {arguments.rounds} epochs each, in turns of {turns}, "
        f"torch {torch.__version__}"
    )
    print(f"{'variant':<26}{'epoch s':>10}{'windows/s':>12}{'speed-up':>10}")
    for name, values in seconds.items():
        print(f"{name:<26}{statistics.median(values):>10.2f}{rates[name]:>12.0f}{speed_ups[name]:>9.2f}x")
    # Each round's loop epoch over its vectorized epoch: how far one round alone can be trusted.
    round_ratios = [
        loop / vectorized for vectorized, loop in zip(seconds[vectorized_name], seconds[loop_name], strict=True)
    ]
    print(
        f"speed-up of single rounds: {min(round_ratios):.1f}x to {max(round_ratios):.1f}x, "
        f"median {statistics.median(round_ratios):.1f}x; vectorized epochs "
        f"{min(seconds[vectorized_name]):.2f}-{max(seconds[vectorized_name]):.2f} s"
    )


if __name__ == "__main__":
    main()
