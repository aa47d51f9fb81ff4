"""Training throughput of the vectorized tokenizer vs a Python loop over A single-dimension tokenizers.

Both variants compute the same math from the same initial weights (the loop's modules are split off the vectorized
one with `carp.tokenizer.per_dimension`): per batch, forward + backward of the summed per-dimension losses and one
AdamW step. Throughput is measured over one epoch of synthetic pick-and-place windows after a short warm-up.

    .venv/bin/python benchmarks/tokenizer_throughput.py [--threads 1] [--batch-size 128] [--episodes 40]
"""

import argparse
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


def epoch_throughput(step, windows: torch.Tensor, batch_size: int) -> tuple[float, float]:
    batches = torch.split(windows[torch.randperm(windows.shape[0])], batch_size)
    for batch in batches[:WARMUP_STEPS]:
        step(batch)
    started = time.perf_counter()
    for batch in batches:
        step(batch)
    seconds = time.perf_counter() - started
    return seconds, windows.shape[0] / seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--batch-size", type=int, default=TokenizerTrainingSettings().batch_size)
    parser.add_argument("--episodes", type=int, default=40, help="synthetic demos (about 118 windows each)")
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

    results = {
        "vectorized (groups=A)": epoch_throughput(
            lambda batch: vectorized_step(vectorized, vectorized_optimizer, batch), windows, arguments.batch_size
        ),
        f"loop over {spec.action_dim} modules": epoch_throughput(
            lambda batch: loop_step(singles, loop_optimizer, batch), windows, arguments.batch_size
        ),
    }
    loop_rate = results[f"loop over {spec.action_dim} modules"][1]
    print(
        f"tokenizer training throughput: A={spec.action_dim}, H={spec.action_horizon}, V={spec.codebook_size}, "
        f"batch {arguments.batch_size}, {windows.shape[0]} windows, {arguments.threads} thread(s), "
        f"torch {torch.__version__}"
    )
    print(f"{'variant':<26}{'epoch s':>10}{'windows/s':>12}{'speed-up':>10}")
    for name, (seconds, rate) in results.items():
        print(f"{name:<26}{seconds:>10.2f}{rate:>12.0f}{rate / loop_rate:>9.1f}x")


if __name__ == "__main__":
    main()
