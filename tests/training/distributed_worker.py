"""One process of the multi-process training tests: a tiny policy trained by the shared loop, under torchrun or alone.

    python distributed_worker.py FAMILY OUTPUT_DIR CHECKPOINT_DIR [--epochs N] [--pause-after-epoch E]

Like `pipeline/train_policy.py` it reads torchrun's variables and joins the process group when they are set. Every
process writes `OUTPUT_DIR/rank<r>.pid` as it starts and `OUTPUT_DIR/rank<r>.json` (the epochs reported to it) as it
ends; rank 0 also writes `policy.pt` (the trained weights). `--pause-after-epoch E` has rank 0 write
`OUTPUT_DIR/paused` once epoch E is reported (its training state is written by then) and wait there to be killed.
"""

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from carp.config import TrainingConfig
from carp.data.normalizer import MinMaxNormalizer
from carp.policies.carp.config import CarpConfig
from carp.policies.context import PolicyContext
from carp.policies.diffusion.config import DiffusionTransformerConfig, DiffusionUNetConfig
from carp.policies.next_token.config import NextTokenConfig
from carp.policies.registry import train_policy
from carp.tokenizer.artifact import TokenizerArtifact
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer
from carp.training import distributed
from carp.training.loop import PolicyTrainingData

OBS_STEPS, OBS_DIM, HORIZON, ACTION_DIM = 2, 3, 8, 2
# 97 windows in batches of 16: the last batch has one window, so with 2 processes one of them gets none.
WINDOWS, BATCH_SIZE = 97, 16
CONFIGS = {
    "carp": CarpConfig(depth=1, width=16, num_heads=2, warmup_steps=2, use_ema=True, ema_decay=0.9),
    "next_token": NextTokenConfig(depth=1, width=16, num_heads=2, warmup_steps=2, use_ema=True, ema_decay=0.9),
    # Dropout and diffusion noise: a loss with random draws in every process.
    "diffusion_transformer": DiffusionTransformerConfig(
        num_layers=1, num_heads=2, width=16, num_train_steps=10, warmup_steps=2, attention_dropout=0.3
    ),
    "diffusion_unet": DiffusionUNetConfig(
        down_dims=(8, 16), num_groups=4, step_embedding_dim=8, num_train_steps=10, warmup_steps=2
    ),
}


def tiny_context() -> tuple[PolicyContext, PolicyTrainingData]:
    """Random normalized windows (N, To, Do) / (N, H, A) and a randomly initialized tokenizer (V = 8, scales (1, 2))."""
    generator = torch.Generator().manual_seed(0)
    data = PolicyTrainingData(
        obs=torch.rand(WINDOWS, OBS_STEPS, OBS_DIM, generator=generator) * 2 - 1,
        actions=torch.rand(WINDOWS, HORIZON, ACTION_DIM, generator=generator) * 2 - 1,
    )
    torch.manual_seed(0)
    spec = TokenizerSpec(action_dim=ACTION_DIM, action_horizon=HORIZON, scales=(1, 2), codebook_size=8,
                         latent_channels=4)  # fmt: skip
    tokenizer = MultiScaleActionTokenizer(spec)
    with torch.no_grad():
        tokenizer.quantizer.codebook.normal_()
    action_normalizer = MinMaxNormalizer(np.full(ACTION_DIM, -1.0), np.full(ACTION_DIM, 1.0))
    artifact = TokenizerArtifact.build(tokenizer.eval(), {"task": action_normalizer}, "test-abs2")
    obs_normalizer = MinMaxNormalizer(np.full(OBS_DIM, -1.0), np.full(OBS_DIM, 1.0))
    context = PolicyContext(obs_normalizer, action_normalizer, OBS_STEPS, HORIZON, tokenizer_artifact=artifact)
    return context, data


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("family", choices=sorted(CONFIGS))
    parser.add_argument("output", type=Path)
    parser.add_argument("checkpoints", type=Path)
    parser.add_argument("--epochs", type=int, default=4)
    parser.add_argument("--pause-after-epoch", type=int, default=0)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    processes = distributed.Processes()
    if "WORLD_SIZE" in os.environ:
        distributed.end_with_launcher()
        processes = distributed.Processes(int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"]))
        distributed.start_process_group(
            processes.rank, processes.world_size, int(os.environ["LOCAL_RANK"]), os.environ["MASTER_ADDR"],
            int(os.environ["MASTER_PORT"]), torch.device("cpu"),
        )  # fmt: skip
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / f"rank{processes.rank}.pid").write_text(str(os.getpid()))
    reported: list[dict] = []

    def on_epoch_end(epoch: int, metrics: dict[str, float]) -> None:
        reported.append({"epoch": epoch, **metrics})
        if epoch + 1 == args.pause_after_epoch:
            (args.output / "paused").touch()
            time.sleep(600)

    training = TrainingConfig(epochs=args.epochs, batch_size=BATCH_SIZE, checkpoint_every=1, seed=3,
                              precision="float32", num_processes=processes.world_size)  # fmt: skip
    context, data = tiny_context()
    policy = train_policy(
        args.family, CONFIGS[args.family], training, context, data, args.checkpoints, on_epoch_end=on_epoch_end
    )
    record = {"world_size": distributed.current_processes().world_size, "reported": reported}
    (args.output / f"rank{processes.rank}.json").write_text(json.dumps(record))
    if processes.is_main:
        torch.save(policy.state_dict(), args.output / "policy.pt")
    distributed.stop_process_group()


if __name__ == "__main__":
    sys.exit(main())
