"""Training throughput of the vectorized tokenizer vs a Python loop over A single-dimension tokenizers.

Both variants are the same class (`MultiScaleActionTokenizer`, the loop's with action_dim = 1) and compute the same
math from the same initial weights (the loop's modules are split off the vectorized one with
`carp.tokenizer.per_dimension`): per batch, forward + backward of the summed per-dimension losses and one fused AdamW
step. Throughput is measured over whole epochs of synthetic pick-and-place windows after a short warm-up; the two
variants alternate epoch by epoch (`--rounds`) so that a change in machine load hits both, and the median epoch of
each is reported. Nine rounds by default: on a shared virtual machine the host's speed drifts by ~10% within a minute,
and 3-round runs of one code spread over 4.4-5.6x where five 9-round runs gave 4.9-5.5x (AVX-512 machine).

    .venv/bin/python benchmarks/tokenizer_throughput.py [--threads 1] [--batch-size 64] [--episodes 40] [--rounds 9]
"""

import argparse
import statistics
import time

import torch

from carp.tokenizer.per_dimension import split_into_single_dimension_tokenizers
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.synthetic import min_max_bounds, sliding_windows, synthetic_action_episodes
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer
from carp.training.tokenizer_trainer import TokenizerTrainingSettings

WARMUP_STEPS = 3


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


def epoch_seconds(step, windows: torch.Tensor, batch_size: int) -> float:
    batches = torch.split(windows[torch.randperm(windows.shape[0])], batch_size)
    for batch in batches[:WARMUP_STEPS]:
        step(batch)
    started = time.perf_counter()
    for batch in batches:
        step(batch)
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--batch-size", type=int, default=TokenizerTrainingSettings().batch_size)
    parser.add_argument("--episodes", type=int, default=40, help="synthetic demos (about 118 windows each)")
    parser.add_argument("--rounds", type=int, default=9, help="epochs per variant, alternating")
    arguments = parser.parse_args()
    torch.set_num_threads(arguments.threads)
    torch.manual_seed(0)

    spec = TokenizerSpec(action_dim=10)
    windows = make_windows(arguments.episodes, spec)
    vectorized = MultiScaleActionTokenizer(spec).train()
    singles = [single.train() for single in split_into_single_dimension_tokenizers(vectorized)]
    # Both use the trainer's optimizer (fused AdamW), so the comparison isolates the model's forward and backward.
    vectorized_optimizer = torch.optim.AdamW(vectorized.parameters(), lr=1e-3, fused=True)
    loop_optimizer = torch.optim.AdamW([p for single in singles for p in single.parameters()], lr=1e-3, fused=True)

    vectorized_name, loop_name = "vectorized (one module)", f"loop over {spec.action_dim} modules"
    steps = {
        vectorized_name: lambda batch: vectorized_step(vectorized, vectorized_optimizer, batch),
        loop_name: lambda batch: loop_step(singles, loop_optimizer, batch),
    }
    seconds: dict[str, list[float]] = {name: [] for name in steps}
    for _ in range(arguments.rounds):
        for name, step in steps.items():
            seconds[name].append(epoch_seconds(step, windows, arguments.batch_size))
    rates = {name: windows.shape[0] / statistics.median(values) for name, values in seconds.items()}
    print(
        f"tokenizer training throughput: A={spec.action_dim}, H={spec.action_horizon}, V={spec.codebook_size}, "
        f"batch {arguments.batch_size}, {windows.shape[0]} windows, {arguments.threads} thread(s), "
        f"median of {arguments.rounds} alternating epochs each, torch {torch.__version__}"
    )
    print(f"{'variant':<26}{'epoch s':>10}{'windows/s':>12}{'speed-up':>10}")
    for name, values in seconds.items():
        speed_up = rates[name] / rates[loop_name]
        print(f"{name:<26}{statistics.median(values):>10.2f}{rates[name]:>12.0f}{speed_up:>9.1f}x")
    # Each round's loop epoch over the vectorized epoch that ran just before it: how much one round can be trusted.
    round_ratios = [
        loop / vectorized for vectorized, loop in zip(seconds[vectorized_name], seconds[loop_name], strict=True)
    ]
    print(
        f"speed-up of single rounds: {min(round_ratios):.1f}x to {max(round_ratios):.1f}x, "
        f"median {statistics.median(round_ratios):.1f}x"
    )


if __name__ == "__main__":
    main()
