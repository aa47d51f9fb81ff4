"""train_tokenizer stage: action windows of tokenizer.tasks -> models/tokenizer/ + metrics, history and figure."""

import numpy as np
import pandas as pd
import torch
from carp.tokenizer.plots import plot_reconstruction
from stage_support import (
    CHECKPOINT_DIR,
    PROCESSED_DIR,
    TOKENIZER_DIR,
    TOKENIZER_REPORT_DIR,
    load,
    mlflow_stage,
    parse_args,
    select_device,
    setup_logging,
    write_json,
)

from carp.data.dataset import load_task_windows, union_normalizer
from carp.tokenizer.artifact import save_tokenizer_artifact
from carp.tokenizer.metrics import reconstruct_trajectory, reconstruction_metrics
from carp.tokenizer.spec import TokenizerSpec
from carp.training.tokenizer_trainer import TokenizerTrainingSettings, train_tokenizer

ABSOLUTE_NAMES = ["x", "y", "z", "rot0", "rot1", "rot2", "rot3", "rot4", "rot5", "gripper"]
DELTA_NAMES = ["dx", "dy", "dz", "drx", "dry", "drz", "gripper"]


def main() -> None:
    setup_logging()
    params = load(parse_args(__doc__).params)
    data, config = params.data, params.tokenizer
    tasks = list(params.tokenizer_tasks)
    windows = [
        load_task_windows(PROCESSED_DIR / task, data.action_horizon, data.obs_steps, data.action_steps)
        for task in tasks
    ]
    normalizer = union_normalizer([w.action_normalizer for w in windows])
    train = torch.as_tensor(
        normalizer.normalize(np.concatenate([w.train_actions for w in windows])), dtype=torch.float32
    )
    valid = torch.as_tensor(
        normalizer.normalize(np.concatenate([w.valid_actions for w in windows])), dtype=torch.float32
    )
    spec = TokenizerSpec(
        action_dim=data.action_dim,
        action_horizon=data.action_horizon,
        scales=params.scales,
        codebook_size=params.codebook_size,
        latent_channels=config.latent_channels,
        base_channels=config.base_channels,
        channel_mult=config.channel_mult,
        commitment_weight=config.commitment_weight,
    )
    settings = TokenizerTrainingSettings(
        epochs=config.epochs,
        batch_size=config.batch_size,
        learning_rate=config.learning_rate,
        weight_decay=config.weight_decay,
        seed=config.seed,
        checkpoint_every=config.checkpoint_every,
        device=str(select_device(params)),
    )
    names = ABSOLUTE_NAMES if data.controller == "absolute" else DELTA_NAMES
    history: list[dict] = []
    with mlflow_stage(params, "train_tokenizer", "tokenizer", {"carp.tasks": ",".join(tasks)}) as run:

        def log_epoch(epoch: int, metrics: dict[str, float]) -> None:
            history.append({"epoch": epoch + 1, **metrics})
            run.log_metrics(metrics, step=epoch + 1)

        tokenizer = train_tokenizer(spec, train, valid, settings, CHECKPOINT_DIR / "tokenizer", on_epoch_end=log_epoch)
        tokenizer = tokenizer.cpu().eval()

        def unnormalize(values: torch.Tensor) -> torch.Tensor:
            return normalizer.unnormalize(values.double()).float()

        metrics = reconstruction_metrics(tokenizer, valid if len(valid) else train, unnormalize, names)
        run.log_metrics({k.replace("/", "."): v for k, v in metrics.items()})

        TOKENIZER_REPORT_DIR.mkdir(parents=True, exist_ok=True)
        write_json(TOKENIZER_REPORT_DIR / "metrics.json", metrics)
        pd.DataFrame(history).to_csv(TOKENIZER_REPORT_DIR / "history.csv", index=False)
        figure = TOKENIZER_REPORT_DIR / "reconstruction.png"
        buffer = windows[0].buffer
        held_out = np.flatnonzero(buffer.valid_episodes)
        episode = int(held_out[0]) if held_out.size else 0
        raw = buffer.episode(episode)[1].astype(np.float64)
        normalized = torch.as_tensor(normalizer.normalize(raw), dtype=torch.float32)
        reconstructed = normalizer.unnormalize(reconstruct_trajectory(tokenizer, normalized).double().numpy())
        plot_reconstruction(raw, reconstructed, figure, names)
        run.log_artifact(figure)

        sha256 = save_tokenizer_artifact(TOKENIZER_DIR, tokenizer, normalizer, params.action_space, tasks)
        run.set_tags({"carp.tokenizer_sha256": sha256})
    print(
        f"tokenizer on {tasks}: {len(train)} train / {len(valid)} held-out windows, mean RMSE "
        f"{metrics['rmse_percent_range/mean']:.2f}% of range (max dim "
        f"{max(metrics[f'rmse_percent_range/{n}'] for n in names):.2f}%), sha256 {sha256[:12]}"
    )


if __name__ == "__main__":
    main()
