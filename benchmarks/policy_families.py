"""Per-chunk latency of every policy family at its default config, side by side, and each family's ratio to CARP.

Builds each registered family at its default params section for Lift's shapes (Do = 19, To = 2, H = 16, A = 10; the
default tokenizer for the token families) with randomly initialized weights (speed does not depend on the values),
and times `predict_action_timed` at batch 1 and at batch 64 in one interleaved run: every round calls each
configuration once, in the same process on the same threads, and the batch-64 rounds are spread among the batch-1
ones, so that a slower or busier stretch of the machine affects every row and both batch sizes alike. Rows:

- `carp` on ONNX Runtime (what evaluation runs) and in PyTorch;
- `diffusion_unet` (DP-C) and `diffusion_transformer` (DP-T) with DDIM-10 and DDPM-100, in PyTorch under inference
  mode (the sampler loop holds one denoiser call and one scheduler update per step);
- `next_token`, greedy, in PyTorch with its kv-cache;
- `vq_bet`, codes sampled, in PyTorch (one GPT call per chunk; its VQ-VAE untrained, which does not change the time);
- `edm_unet` (Consistency Policy's teacher, Heun-80: 158 U-Net calls) and `consistency_policy` one-step and
  three-step, in PyTorch; the one-step row is the speed CARP's claim is measured against.

Each batch size has its ratio column: a row's median over CARP's at that batch size (CARP on ONNX Runtime at batch
1, CARP in PyTorch at batch 64, as the ONNX Runtime graphs are exported for batch 1). The issue's targets on the
2-core CPU are CARP at least 10x faster than DP-T with DDIM-10 and at least 100x faster than DP-C with DDPM-100;
this script prints the numbers and asserts nothing.

Usage: python benchmarks/policy_families.py [--rounds 20] [--batched-rounds 3] [--threads 1] [--skip-batched]
                                            [--tiny]
`--tiny` shrinks every family (a smoke run for tests, not a measurement).
"""

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from carp.data.normalizer import MinMaxNormalizer
from carp.evaluation.runner import deploy
from carp.policies.context import PolicyContext
from carp.policies.registry import build_policy, family_names, get_family, load_policy
from carp.tokenizer.artifact import TokenizerArtifact
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer

OBS_DIM, OBS_STEPS, ACTION_HORIZON, ACTION_DIM = 19, 2, 16, 10
TINY_SECTIONS = {
    "carp": {"depth": 1, "width": 16, "num_heads": 2},
    "diffusion_unet": {"down_dims": [16, 32], "kernel_size": 3, "step_embedding_dim": 16, "num_train_steps": 10},
    "diffusion_transformer": {"num_layers": 1, "num_heads": 2, "width": 16, "num_train_steps": 10},
    "next_token": {"depth": 1, "width": 16, "num_heads": 2},
    "vq_bet": {"depth": 1, "width": 16, "num_heads": 2, "output_width": 16, "head_hidden_width": 32},
    "edm_unet": {"down_dims": [16, 32], "kernel_size": 3, "step_embedding_dim": 16},
    "consistency_policy": {"down_dims": [16, 32], "kernel_size": 3, "step_embedding_dim": 16},
}
INFERENCE_VARIANTS = {
    "diffusion_unet": ({"sampler": "ddim", "num_inference_steps": 10}, {"sampler": "ddpm", "num_inference_steps": 100}),
    "diffusion_transformer": (
        {"sampler": "ddim", "num_inference_steps": 10},
        {"sampler": "ddpm", "num_inference_steps": 100},
    ),
    "consistency_policy": ({"chain_levels": ()}, {"chain_levels": (27, 54)}),
}
"""Inference settings timed per family (the family's defaults when absent): both samplers of the issue's targets."""
REFERENCE = "carp"
BATCH = 64
"""The batched size: evaluation's many environments stepped together, as a vectorized executor would."""


def context(tiny: bool) -> PolicyContext:
    """Lift's shapes with identity-like normalizers and the default (or a tiny) tokenizer."""
    spec = TokenizerSpec(action_dim=ACTION_DIM, codebook_size=16 if tiny else 512)
    action_normalizer = MinMaxNormalizer(np.full(ACTION_DIM, -1.0), np.full(ACTION_DIM, 1.0))
    artifact = TokenizerArtifact.build(MultiScaleActionTokenizer(spec), {"lift": action_normalizer}, "panda-abs10")
    return PolicyContext(
        obs_normalizer=MinMaxNormalizer(np.full(OBS_DIM, -1.0), np.full(OBS_DIM, 1.0)),
        action_normalizer=action_normalizer,
        obs_steps=OBS_STEPS,
        action_horizon=ACTION_HORIZON,
        tokenizer_artifact=artifact,
    )


def configurations(tiny: bool, directory: Path) -> list[tuple[str, str, object]]:
    """(family, backend, policy) of every row: each family and inference variant in PyTorch, plus the backend its
    evaluation deploys when that is another one (CARP's ONNX Runtime graphs); the reference row comes first."""
    torch.manual_seed(0)
    shapes = context(tiny)
    rows = []
    for name in family_names():
        config = get_family(name).config_class(**(TINY_SECTIONS.get(name, {}) if tiny else {}))
        trained = build_policy(name, config, shapes)
        checkpoint = Path(directory) / f"{name}.pt"
        trained.save(checkpoint)
        for settings in INFERENCE_VARIANTS.get(name, ({},)):
            if "num_inference_steps" in settings:  # a tiny schedule has fewer steps than the paper's sampler
                settings = settings | {
                    "num_inference_steps": min(settings["num_inference_steps"], config.num_train_steps)
                }
            for backend in ("onnxruntime", "torch"):
                policy = load_policy(checkpoint)
                policy.configure_inference(**settings)
                deployment = deploy(policy, checkpoint, backend, Path(directory) / f"{name}-{len(rows)}")
                if backend == "torch" or deployment.backend != "torch":
                    deployed = deployment.load()
                    deployed.configure_inference(**settings)
                    row = (name, deployment.backend, deployed)
                    reference = (name, deployment.backend) == (REFERENCE, "onnxruntime")
                    rows.insert(0 if reference else len(rows), row)
    return rows


def spread(count: int, total: int) -> set[int]:
    """`count` round indices spread evenly over `total` rounds (`count` <= `total`)."""
    return {index * total // count for index in range(count)}


def time_rows(rows: list, rounds: int, batched_rounds: int | None) -> dict[int, list[list[float]]]:
    """Interleaved timing at batch 1 and 64: ms per call, per batch size and row.

    Every round calls each row once on the same (B, To, Do) observations; the batch-64 calls are spread evenly over
    the batch-1 rounds, so both batch sizes are measured over the same stretch of the machine's load. A row that
    does not run at a batch size gets an empty list (CARP's ONNX Runtime graphs are exported for one environment,
    batch 1, as evaluation runs them). `batched_rounds` None times batch 1 only.
    """
    counts = {1: rounds} if batched_rounds is None else {1: rounds, BATCH: batched_rounds}
    total = max(counts.values())
    schedule = {batch_size: spread(count, total) for batch_size, count in counts.items()}
    generator = np.random.default_rng(0)
    observations = {
        batch_size: generator.uniform(-1, 1, size=(batch_size, OBS_STEPS, OBS_DIM)).astype(np.float32)
        for batch_size in counts
    }
    runs = {batch_size: [batch_size == 1 or backend == "torch" for _, backend, _ in rows] for batch_size in counts}
    for batch_size, obs in observations.items():  # warm-up: first-call allocations
        for (_, _, policy), included in zip(rows, runs[batch_size], strict=True):
            if included:
                policy.predict_action_timed(obs, generator=torch.Generator().manual_seed(0))
    timings = {batch_size: [[] for _ in rows] for batch_size in counts}
    for round_index in range(total):
        for batch_size, obs in observations.items():
            if round_index not in schedule[batch_size]:
                continue
            for index, (_, _, policy) in enumerate(rows):
                if not runs[batch_size][index]:
                    continue
                started = time.perf_counter()
                policy.predict_action_timed(obs, generator=torch.Generator().manual_seed(round_index))
                timings[batch_size][index].append(1e3 * (time.perf_counter() - started))
    return timings


def percentile(values: list[float], fraction: float) -> float:
    """The `fraction` quantile (nearest rank) of `values`."""
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(round(fraction * (len(ordered) - 1))))]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=20, help="timed calls per row at batch 1")
    parser.add_argument("--batched-rounds", type=int, default=3, help="timed calls per row at batch 64")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads for every row")
    parser.add_argument("--skip-batched", action="store_true", help="time batch 1 only")
    parser.add_argument("--tiny", action="store_true", help="tiny configs: a smoke run, not a measurement")
    args = parser.parse_args()
    if args.rounds < 1 or args.batched_rounds < 1 or args.threads < 1:
        print("error: --rounds, --batched-rounds and --threads must be >= 1", file=sys.stderr)
        return 1
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory(prefix="carp-families-") as directory:
        rows = configurations(args.tiny, Path(directory))
        timings = time_rows(rows, args.rounds, None if args.skip_batched else args.batched_rounds)
    single, batched = timings[1], timings.get(BATCH)
    # CARP's fastest row at each batch size: ONNX Runtime at batch 1 (first row), PyTorch at 64 (no batched graphs).
    reference = statistics.median(single[0])
    batched_reference = None
    if batched is not None:
        carp_batched = [times for (name, _, _), times in zip(rows, batched, strict=True) if name == REFERENCE and times]
        batched_reference = statistics.median(carp_batched[0])
    size = "tiny configs" if args.tiny else "default configs"
    print(
        f"policy families, {size}, Lift shapes (Do={OBS_DIM}, To={OBS_STEPS}, H={ACTION_HORIZON}, A={ACTION_DIM}), "
        f"{args.threads} thread(s), torch {torch.__version__}, {args.rounds} interleaved rounds at batch 1"
        + ("" if batched is None else f", {args.batched_rounds} at batch {BATCH} among them")
    )
    header = (
        f"| {'family':<22} | {'inference':<9} | {'backend':<11} | {'parameters':>11} | {'calls':>5} | "
        f"{'B=1 median ms':>13} | {'B=1 p90 ms':>10} | {'B=1 x CARP':>10} | {f'B={BATCH} ms/chunk':>13} | "
        f"{f'B={BATCH} x CARP':>11} |"
    )
    print(header)
    print("|" + "|".join("-" * len(cell) for cell in header.split("|")[1:-1]) + "|")
    for index, (name, backend, policy) in enumerate(rows):
        median = statistics.median(single[index])
        per_chunk, batched_ratio = "-", "-"
        if batched is not None and batched[index]:
            batched_median = statistics.median(batched[index])
            per_chunk, batched_ratio = f"{batched_median / BATCH:.3f}", f"{batched_median / batched_reference:.1f}"
        print(
            f"| {name:<22} | {policy.description:<9} | {backend:<11} | {policy.num_parameters:>11,} | "
            f"{policy.model_calls_per_chunk:>5} | {median:13.3f} | {percentile(single[index], 0.9):10.3f} | "
            f"{median / reference:10.1f} | {per_chunk:>13} | {batched_ratio:>11} |"
        )
    print(
        f"x CARP: the row's median over CARP's at the same batch size (batch 1: CARP on ONNX Runtime, the first row; "
        f"batch {BATCH}: CARP in PyTorch, as its ONNX Runtime graphs are exported for batch 1)."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
