"""Speed of the coarse-to-fine policy for the default configuration (A = 10, L = 100, depth 8, D = 64, 8 heads).

Measures, with randomly initialized weights (speed does not depend on the values):
- per-chunk latency at batch 1 on one CPU thread: prediction (normalization + K = 4 steps with the kv-cache) and
  decoding (tokenizer decoder + un-normalization), median and p90, for the PyTorch policy and for the ONNX Runtime
  graphs that evaluation runs by default (`carp.policies.carp.onnx_policy`, exported here first, ~1-2 s each), greedy
  and with top-k draws (`--top-k`);
- the same at batch 64 (latency of one call and per chunk);
- training throughput at batch 256 on two threads: forward, cross-entropy, backward and AdamW step on precomputed
  token targets, as the shared loop runs CARP's step (`carp.policies.carp.trainer`), in float32 and in the precision
  `training.precision: auto` picks here (bfloat16 autocast on CPUs with native bfloat16 matmuls); steps of the two
  alternate;
- with --compare-attention, only training: float32 steps with each block-causal attention kernel (`carp.attention`),
  interleaved, at several batch sizes, beside the kernel `auto` would choose from its own short measurement.

Reference (issue text): the official implementation needs 21.8 ms per chunk (17.8 ms prediction + 4.0 ms decoding)
and 2.6 s per training step at batch 256 on 2 threads.

Usage: python benchmarks/policy_speed.py [--chunks 300] [--train-steps 8] [--skip-training] [--skip-onnx] [--top-k 3]
       python benchmarks/policy_speed.py --compare-attention [--attention-batches 64 256] [--train-steps 8]
"""

import argparse
import statistics
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from carp.data.normalizer import MinMaxNormalizer
from carp.policies.carp.attention import ATTENTION_KERNELS, faster_kernel
from carp.policies.carp.config import CarpConfig
from carp.policies.carp.onnx_policy import OnnxPolicy, export_policy_graphs
from carp.policies.carp.policy import CarpPolicy
from carp.policies.carp.spec import PolicySpec
from carp.policies.carp.trainer import measure_attention_kernels, optimizer_recipe, teacher_forced_step
from carp.policies.carp.transformer import CoarseToFineTransformer
from carp.tokenizer.artifact import TokenizerArtifact
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer
from carp.training.loop import make_optimizer
from carp.training.runtime import autocast_to, precision_name, resolve_precision

OBS_DIM = 19  # Lift's low-dim observation width
OBS_STEPS = 2
OFFICIAL_CHUNK_MS = (21.8, 17.8, 4.0)
OFFICIAL_TRAIN_STEP_SECONDS = 2.6


def make_policy() -> CarpPolicy:
    torch.manual_seed(0)
    tokenizer_spec = TokenizerSpec(action_dim=10)
    spec = PolicySpec(
        obs_dim=OBS_DIM,
        obs_steps=OBS_STEPS,
        action_dim=tokenizer_spec.action_dim,
        scales=tokenizer_spec.scales,
        latent_channels=tokenizer_spec.latent_channels,
        codebook_size=tokenizer_spec.codebook_size,
    )
    action_normalizer = MinMaxNormalizer(np.full(10, -1.0), np.full(10, 1.0))
    return CarpPolicy(
        TokenizerArtifact.build(MultiScaleActionTokenizer(tokenizer_spec), {"lift": action_normalizer}, "panda-abs10"),
        CoarseToFineTransformer(spec),
        MinMaxNormalizer(np.full(OBS_DIM, -1.0), np.full(OBS_DIM, 1.0)),
        action_normalizer,
    )


def time_chunks(policy: CarpPolicy | OnnxPolicy, batch_size: int, calls: int) -> dict[str, list[float]]:
    rng = np.random.default_rng(0)
    obs = rng.uniform(-1, 1, size=(batch_size, OBS_STEPS, OBS_DIM)).astype(np.float32)
    for _ in range(max(10, calls // 10)):
        policy.predict_action_timed(obs)
    timings = {"total": [], "prediction": [], "decoding": [], "cpu": []}
    for _ in range(calls):
        cpu_started = time.thread_time()
        timed = policy.predict_action_timed(obs)
        prediction, decoding = timed.prediction_seconds, timed.decoding_seconds
        timings["cpu"].append((time.thread_time() - cpu_started) * 1e3)
        timings["prediction"].append(prediction * 1e3)
        timings["decoding"].append(decoding * 1e3)
        timings["total"].append((prediction + decoding) * 1e3)
    return timings


def percentile(values: list[float], fraction: float) -> float:
    return float(np.percentile(values, 100 * fraction))


class TrainingVariant(NamedTuple):
    """One way of running the training step: its autocast precision and its attention kernel."""

    precision: torch.dtype
    attention: str = "masked"

    def label(self, auto_precision: torch.dtype) -> str:
        name = precision_name(self.precision) + (" (auto)" if self.precision == auto_precision else "")
        return f"{name}, {self.attention} attention"


def train_steps_seconds(policy: CarpPolicy, batch_size: int, steps: int, variants: list[TrainingVariant]) -> dict:
    """Median wall and CPU seconds per training step (all threads) per variant, steps alternating between them."""
    spec = policy.spec
    generator = torch.Generator().manual_seed(0)
    obs = torch.randn(batch_size, OBS_STEPS, OBS_DIM, generator=generator)
    teacher = torch.randn(batch_size, spec.sequence_length - spec.scales[0] * spec.action_dim, spec.latent_channels)
    targets = torch.randint(spec.codebook_size, (batch_size, spec.sequence_length), generator=generator)
    batch = {"obs": obs, "teacher_inputs": teacher, "token_sequence": targets}

    def make_step(variant: TrainingVariant):
        torch.manual_seed(0)
        transformer = CoarseToFineTransformer(spec).train()
        transformer.attention_kernel = variant.attention
        recipe = optimizer_recipe(transformer, CarpConfig())
        optimizer = make_optimizer(recipe.parameter_groups(), recipe, torch.device("cpu"))

        def step() -> None:
            with autocast_to(variant.precision, torch.device("cpu")):
                loss = teacher_forced_step(transformer, batch).loss
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()

        return step

    runs = {variant: make_step(variant) for variant in variants}
    for step in runs.values():
        for _ in range(2):
            step()
    durations = {variant: ([], []) for variant in variants}
    for _ in range(steps):
        for variant, step in runs.items():
            started, cpu_started = time.perf_counter(), time.process_time()
            step()
            durations[variant][0].append(time.perf_counter() - started)
            durations[variant][1].append(time.process_time() - cpu_started)
    return {variant: (statistics.median(wall), statistics.median(cpu)) for variant, (wall, cpu) in durations.items()}


def print_training(timings: dict, batch_size: int, auto: torch.dtype) -> None:
    """One line per variant: seconds per step, samples/s and the speed-up over the official step at batch 256."""
    for variant, (seconds, cpu_seconds) in timings.items():
        line = (
            f"  {variant.label(auto):<36} {seconds:.3f} s per step ({cpu_seconds:.3f} CPU s over all threads), "
            f"{batch_size / seconds:.0f} samples/s"
        )
        if batch_size == 256:
            line += f", speed-up x{OFFICIAL_TRAIN_STEP_SECONDS / seconds:.2f}"
        print(line)


def compare_attention(policy: CarpPolicy, batch_sizes: list[int], steps: int, threads: int) -> None:
    """Both attention kernels: whole float32 training steps, interleaved, and what `carp.attention: auto` measures."""
    transformer = CoarseToFineTransformer(policy.spec)
    variants = [TrainingVariant(torch.float32, kernel) for kernel in ATTENTION_KERNELS]
    print(f"attention kernels, float32 training steps on {threads} threads, interleaved, median of {steps}:")
    print(
        f"| {'batch':>5} | {'masked s/step':>13} | {'blockwise s/step':>16} | {'blockwise/masked':>16} "
        "| auto measures |"
    )
    print(f"|{'-' * 7}|{'-' * 15}|{'-' * 18}|{'-' * 18}|{'-' * 15}|")
    for batch_size in batch_sizes:
        timings = train_steps_seconds(policy, batch_size, steps, variants)
        masked, blockwise = (timings[variant][0] for variant in variants)
        chosen = faster_kernel(measure_attention_kernels(transformer, batch_size, torch.device("cpu"), torch.float32))
        print(
            f"| {batch_size:>5} | {masked:>13.3f} | {blockwise:>16.3f} | {blockwise / masked:>16.3f} | {chosen:<13} |"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--chunks", type=int, default=300, help="timed calls at batch 1")
    parser.add_argument("--batched-calls", type=int, default=30, help="timed calls at batch 64")
    parser.add_argument("--train-steps", type=int, default=8, help="timed training steps at batch 256 per precision")
    parser.add_argument("--skip-training", action="store_true")
    parser.add_argument("--skip-onnx", action="store_true", help="skip the ONNX Runtime rows (export takes ~1-2 s)")
    parser.add_argument("--top-k", type=int, default=3, help="the sampling graph timed next to the greedy one")
    parser.add_argument(
        "--compare-attention",
        action="store_true",
        help="only time training steps with each attention kernel (carp.attention), at --attention-batches",
    )
    parser.add_argument("--attention-batches", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--threads", type=int, default=2, help="threads of the training measurements")
    args = parser.parse_args()

    if args.compare_attention:
        torch.set_num_threads(args.threads)
        compare_attention(make_policy(), args.attention_batches, args.train_steps, args.threads)
        return

    policy = make_policy()
    rows = []
    torch.set_num_threads(1)
    single = time_chunks(policy, 1, args.chunks)
    for part in ("total", "prediction", "decoding"):
        rows.append((f"batch 1, 1 thread: {part} per chunk (ms)", single[part], 1))
    # Thread CPU time excludes time spent descheduled, a better estimate when other work shares the cores.
    rows.append(("batch 1, 1 thread: CPU time per chunk (ms)", single["cpu"], 1))
    if not args.skip_onnx:
        for top_k in sorted({1, args.top_k}):  # greedy, then the sampling graph (once if --top-k 1)
            with tempfile.TemporaryDirectory(prefix="carp-onnx-") as directory:
                onnx_policy = OnnxPolicy(export_policy_graphs(policy, Path(directory), top_k))
                onnx = time_chunks(onnx_policy, 1, args.chunks)
            choice = "greedy" if top_k == 1 else f"top-{top_k} draws"
            for part in ("total", "prediction", "decoding"):
                rows.append((f"batch 1, 1 thread, onnxruntime, {choice}: {part} per chunk (ms)", onnx[part], 1))
    batched = time_chunks(policy, 64, args.batched_calls)
    rows.append(("batch 64, 1 thread: total per call (ms)", batched["total"], 1))
    rows.append(("batch 64, 1 thread: total per chunk (ms)", batched["total"], 64))
    rows.append(("batch 64, 1 thread: decoding per call (ms)", batched["decoding"], 1))

    print(
        f"policy speed, default config (A=10, L={policy.spec.sequence_length}, depth 8, D 64, 8 heads), torch "
        f"{torch.__version__}"
    )
    print(f"| {'measurement':<72} | {'median':>8} | {'p90':>8} |")
    print(f"|{'-' * 74}|{'-' * 10}|{'-' * 10}|")
    for name, values, divisor in rows:
        median, p90 = statistics.median(values) / divisor, percentile(values, 0.9) / divisor
        print(f"| {name:<72} | {median:8.3f} | {p90:8.3f} |")
    print(
        f"official per chunk at batch 1: {OFFICIAL_CHUNK_MS[0]} ms ({OFFICIAL_CHUNK_MS[1]} prediction + "
        f"{OFFICIAL_CHUNK_MS[2]} decoding)"
    )

    if not args.skip_training:
        torch.set_num_threads(args.threads)
        auto = resolve_precision("auto", torch.device("cpu"))
        variants = [TrainingVariant(precision) for precision in dict.fromkeys([torch.float32, auto])]
        timings = train_steps_seconds(policy, 256, args.train_steps, variants)
        print(
            f"training at batch 256, 2 threads (official: {OFFICIAL_TRAIN_STEP_SECONDS} s per step = "
            f"{256 / OFFICIAL_TRAIN_STEP_SECONDS:.0f} samples/s):"
        )
        print_training(timings, 256, auto)


if __name__ == "__main__":
    main()
