"""Rate and distortion of every tokenizer kind over its own rate knob, and open-loop replay through each round trip.

On one task's ingested demos (``data/processed/<task>/``, ``data/raw/<task>.hdf5``): each kind is fitted on the
training windows at every setting of its rate knob (the rest of its settings from params.yaml's
``tokenizer.<kind>`` section), then measured on the held-out windows by `carp.tokenizer.rate_distortion` (bits per
chunk as tokens x log2 V and as the entropy of the tokens used; RMSE in % of each dimension's range, mean and worst
dimension; encode and decode time per chunk; share of repaired decodes) and, with ``--replay-demos``, by the success
of the first demos replayed open loop through its round trip (`carp.evaluation.replay`). ``carp_msvq`` is trained
with the pipeline's trainer and the ``tokenizer`` section (``--msvq-epochs`` epochs) at each codebook size, or read
from the artifact folders given with ``--carp-msvq``. Run it in a pipeline directory; timings depend on the load.

    .venv/bin/python benchmarks/tokenizer_kinds.py --task lift [--kinds binning fast bspline fsq carp_msvq]
        [--carp-msvq models/tokenizer] [--msvq-epochs 20] [--replay-demos 50] [--workers 2] [--params params.yaml]
"""

import argparse
import dataclasses
import os
import tempfile
from pathlib import Path

import numpy as np
import torch

from carp.config import load_params
from carp.config.tokenizer_kinds import kind_section
from carp.data.dataset import load_task_windows
from carp.evaluation.replay import replay_demonstrations
from carp.tasks import get_task
from carp.tokenizer.kinds.carp_msvq import CarpMsvqTokenizer
from carp.tokenizer.kinds.registry import build_tokenizer, kind_names
from carp.tokenizer.rate_distortion import measure_rate_distortion
from carp.tokenizer.spec import TokenizerSpec
from carp.training.tokenizer_trainer import train_tokenizer

KNOBS = {
    "binning": ("bins", [16, 32, 64, 128, 256]),
    "fast": ("scale", [2.0, 5.0, 10.0, 20.0, 50.0]),
    "bspline": ("control_points", [4, 6, 8, 12, 16]),
    "fsq": ("levels", [(5, 5, 5), (8, 6, 5), (8, 8, 8, 6, 5)]),
    "carp_msvq": ("codebook_size", [64, 512]),
    "joint_msvq": ("codebook_size", [64, 512]),
    "residual_vq": ("num_layers", [2, 4, 8]),
}
"""Kind -> (its rate knob, the settings swept)."""


def carp_msvq_tokenizers(arguments, params, train: torch.Tensor, valid: torch.Tensor, action_dim: int):
    """(codebook size, tokenizer) pairs: the artifacts given, or ones trained here at each swept codebook size."""
    if arguments.carp_msvq:
        for directory in arguments.carp_msvq:
            tokenizer = CarpMsvqTokenizer.from_artifact(directory)
            yield tokenizer.vocabulary_size, tokenizer
        return
    config = dataclasses.replace(params.tokenizer, epochs=arguments.msvq_epochs)
    for codebook_size in KNOBS["carp_msvq"][1]:
        spec = TokenizerSpec(
            action_dim=action_dim,
            action_horizon=params.data.action_horizon,
            scales=params.scales,
            codebook_size=codebook_size,
            latent_channels=config.latent_channels,
            base_channels=config.base_channels,
            channel_mult=config.channel_mult,
            commitment_weight=config.commitment_weight,
        )
        with tempfile.TemporaryDirectory() as checkpoints:
            module = train_tokenizer(spec, train, valid, config, Path(checkpoints))
        yield codebook_size, CarpMsvqTokenizer(module.cpu())


def kind_tokenizers(kind: str, arguments, params, train: torch.Tensor, valid: torch.Tensor, action_dim: int):
    """(knob value, fitted tokenizer) pairs of one kind over its swept settings."""
    if kind == "carp_msvq":
        yield from carp_msvq_tokenizers(arguments, params, train, valid, action_dim)
        return
    knob, values = KNOBS[kind]
    for value in values:
        section = dataclasses.replace(getattr(params, kind_section(kind)), **{knob: value})
        try:
            tokenizer = build_tokenizer(kind, section, action_dim, params.data.action_horizon)
            tokenizer.fit(train)
        except ValueError as error:
            print(f"{kind} {knob}={value}: skipped ({error})")
            continue
        yield value, tokenizer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", required=True, help="a task with data/processed/<task>/ and data/raw/<task>.hdf5")
    parser.add_argument("--kinds", nargs="*", default=list(kind_names()), choices=kind_names())
    parser.add_argument("--carp-msvq", nargs="*", type=Path, default=[], help="artifact folders instead of training")
    parser.add_argument("--msvq-epochs", type=int, default=20)
    parser.add_argument("--replay-demos", type=int, default=0, help="0 skips the replay")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--params", type=Path, default=Path("params.yaml"))
    arguments = parser.parse_args()
    torch.set_num_threads(1)
    params = load_params(arguments.params)
    data = params.data
    windows = load_task_windows(
        Path("data/processed") / arguments.task, data.action_horizon, data.obs_steps, data.action_steps
    )
    normalizer = windows.action_normalizer

    def normalized(actions: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(normalizer.normalize(actions.astype(np.float64)), dtype=torch.float32)

    train, valid = normalized(windows.train_actions), normalized(windows.valid_actions)
    action_dim = train.shape[-1]
    names = get_task(arguments.task).action_format(data.controller).dimension_names or [
        f"dim{index}" for index in range(action_dim)
    ]
    replay_settings = (data.obs_steps, data.action_steps, data.action_horizon)
    raw_path = Path("data/raw") / f"{arguments.task}.hdf5"

    def replay(tokenizer) -> str:
        if not arguments.replay_demos:
            return "-"
        results = replay_demonstrations(
            raw_path,
            normalizer,
            tokenizer,
            *replay_settings,
            num_demos=arguments.replay_demos,
            workers=arguments.workers,
        )
        return f"{sum(result.success for result in results)}/{len(results)}"

    print(
        f"{arguments.task}: {len(train)} training and {len(valid)} held-out windows, H={data.action_horizon}, "
        f"A={action_dim}; replay of the first {arguments.replay_demos} demos with To, Ta, H = {replay_settings}"
    )
    print(f"recorded actions, replayed unchanged: {replay(None)}")
    header = (
        "| kind | knob | V | tokens/chunk (mean, p95) | bits/chunk | entropy bits/chunk | RMSE % range (mean) "
        "| worst dim (RMSE %) | encode ms | decode ms | invalid | replay |"
    )
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for kind in arguments.kinds:
        knob = KNOBS[kind][0]
        for value, tokenizer in kind_tokenizers(kind, arguments, params, train, valid, action_dim):
            measured = measure_rate_distortion(tokenizer, valid)
            setting = f"{knob}={list(value) if isinstance(value, tuple) else value}"
            print(
                f"| {kind} | {setting} | {measured.vocabulary_size} | {measured.tokens_mean:.1f}, "
                f"{measured.tokens_p95:.0f} | {measured.bits_per_chunk:.0f} | {measured.entropy_bits_per_chunk:.0f} "
                f"| {measured.rmse_percent_mean:.2f} | {names[measured.worst_dimension]} "
                f"({measured.worst_rmse_percent:.2f}) | {measured.encode_ms:.3f} | {measured.decode_ms:.3f} "
                f"| {100 * measured.invalid_rate:.0f}% | {replay(tokenizer)} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
