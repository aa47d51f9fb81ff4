"""train_tokenizer stage: action windows of tokenizer.tasks -> models/tokenizer/ + metrics, history and figure.

The kind is ``tokenizer.kind``: ``carp_msvq`` trains CARP's multi-scale VQ-VAE for ``tokenizer.epochs``; another
kind is fitted by its own ``fit`` with its section ``tokenizer_<kind>`` (no epochs, so its history is empty) and
measured by its rate and distortion (`carp.tokenizer.kinds.evaluation`). With ``tokenizer.source:
models:/<name>@<alias>`` nothing is trained: the registered tokenizer is fetched (its sha256 checked), refused in one
line unless its kind and action space (and for carp_msvq its scales and codebook size) fit the params, and measured
on this pipeline's held-out windows, so a reused tokenizer's fit to the new task is on record.
"""

import tempfile
from pathlib import Path

import numpy as np
import torch
from stage_support import (
    CHECKPOINT_DIR,
    PROCESSED_DIR,
    TOKENIZER_DIR,
    TOKENIZER_REPORT_DIR,
    copy_fields,
    fail,
    load,
    mlflow_stage,
    parse_args,
    select_device,
    setup_logging,
    tracking_uri,
)

from carp.config.tokenizer_kinds import DEFAULT_TOKENIZER_KIND
from carp.data.dataset import load_task_windows
from carp.outputs import write_history, write_json
from carp.tokenizer.artifact import (
    NonFiniteTokenizerError,
    TokenizerMismatchError,
    save_tokenizer_artifact,
)
from carp.tokenizer.evaluation import dimension_names, evaluate_tokenizer, summary_line
from carp.tokenizer.kinds.artifact import check_fits_params, save_kind_artifact
from carp.tokenizer.kinds.evaluation import evaluate_kind
from carp.tokenizer.kinds.registry import build_tokenizer
from carp.tokenizer.spec import TokenizerSpec
from carp.tracking.registry import fetch_registered_tokenizer
from carp.training.checkpoint import one_line
from carp.training.tokenizer_trainer import train_tokenizer


def main() -> None:
    setup_logging()
    # One thread: the tokenizer's steps are hundreds of small ops, where a second thread gains little even when the
    # cores are free, but its OpenMP threads wait for each other at every op: passively that makes two threads
    # slower than one, and spinning stalls them many times over as soon as another job uses a core.
    torch.set_num_threads(1)
    params = load(parse_args(__doc__).params)
    data, config = params.data, params.tokenizer
    tasks = list(params.tokenizer_tasks)
    windows = {
        task: load_task_windows(PROCESSED_DIR / task, data.action_horizon, data.obs_steps, data.action_steps)
        for task in tasks
    }
    if config.kind != DEFAULT_TOKENIZER_KIND:
        train_kind(params, windows)
        return
    # Every task is normalized with its own statistics, in training and in every policy (carp.tokenizer.artifact).
    own_normalizers = {task: task_windows.action_normalizer for task, task_windows in windows.items()}
    history: list[dict] = []
    with mlflow_stage(params, "train_tokenizer", "tokenizer", {"carp.tokenizer_source": config.source}) as run:
        if config.source == "pipeline":
            spec = copy_fields(
                TokenizerSpec,
                config,
                action_dim=params.action_format.policy_dim,
                action_horizon=data.action_horizon,
                scales=params.scales,
                codebook_size=params.codebook_size,
            )

            def log_epoch(epoch: int, metrics: dict[str, float]) -> None:
                history.append({"epoch": epoch + 1, **metrics})
                run.log_metrics(metrics, step=epoch + 1)

            def normalized(name: str) -> torch.Tensor:
                values = [
                    own_normalizers[task].normalize(getattr(w, name).astype(np.float64)) for task, w in windows.items()
                ]
                return torch.as_tensor(np.concatenate(values), dtype=torch.float32)

            try:
                tokenizer = train_tokenizer(
                    spec,
                    normalized("train_actions"),
                    normalized("valid_actions"),
                    config,
                    CHECKPOINT_DIR / "tokenizer",
                    on_epoch_end=log_epoch,
                    device=select_device(params),
                ).cpu()
            except NonFiniteTokenizerError as error:
                fail(str(error))
            trained_with = own_normalizers
        else:
            try:
                artifact, reference = fetch_registered_tokenizer(tracking_uri(params), config.source)
            except (LookupError, TokenizerMismatchError, NonFiniteTokenizerError) as error:
                fail(str(error))
            refuse_unfit(artifact, params)
            tokenizer, trained_with = artifact.tokenizer, artifact.action_normalizers
            run.set_tags({"carp.tokenizer_version": reference.version})

        held_out = {task: w.valid_actions if len(w.valid_actions) else w.train_actions for task, w in windows.items()}
        buffer = windows[tasks[0]].buffer
        episode = int(np.flatnonzero(buffer.valid_episodes)[0]) if buffer.valid_episodes.any() else 0
        figure = TOKENIZER_REPORT_DIR / "reconstruction.png"
        figure_episode = (tasks[0], buffer.episode(episode)[1])
        metrics = evaluate_tokenizer(
            tokenizer.eval(), held_out, own_normalizers, figure_episode, figure, params.action_format.dimension_names
        )
        try:
            sha256 = save_tokenizer_artifact(TOKENIZER_DIR, tokenizer, trained_with, params.action_space, metrics)
        except NonFiniteTokenizerError as error:
            figure.unlink(missing_ok=True)
            fail(str(error))
        run.log_metrics({key.replace("/", "."): value for key, value in metrics.items()})
        run.log_artifact(figure)
        run.set_tags({"carp.tokenizer_sha256": sha256})
    write_json(TOKENIZER_REPORT_DIR / "metrics.json", metrics)
    write_history(TOKENIZER_REPORT_DIR / "history.csv", history)
    action = "trained on" if config.source == "pipeline" else f"fetched {config.source}, trained on"
    names = dimension_names(tokenizer.spec.action_dim, params.action_format.dimension_names)
    print(f"tokenizer {action} {list(trained_with)}: {summary_line(metrics, names)} on {tasks}; sha256 {sha256[:12]}")


def refuse_unfit(artifact, params) -> None:
    """Stop with one line naming the registered model, the key and both values when it does not fit the params."""
    try:
        check_fits_params(
            artifact,
            params.tokenizer.kind,
            params.action_space,
            params.data.action_horizon,
            params.scales,
            params.codebook_size,
        )
    except TokenizerMismatchError as error:
        fail(f"{params.tokenizer.source}: {error}")


def train_kind(params, windows: dict) -> None:
    """Fit (or fetch) a kind other than carp_msvq, measure it on held-out windows and save it as the stage's output."""
    config, tasks = params.tokenizer, list(windows)
    normalizers = {task: task_windows.action_normalizer for task, task_windows in windows.items()}
    with (
        mlflow_stage(params, "train_tokenizer", "tokenizer", {"carp.tokenizer_source": config.source}) as run,
        tempfile.TemporaryDirectory(prefix="carp-tokenizer-") as download,
    ):
        run.set_tags({"carp.tokenizer_kind": config.kind})
        files_from = None
        if config.source == "pipeline":
            tokenizer = build_tokenizer(
                config.kind, params.tokenizer_kind_config, params.action_format.policy_dim, params.data.action_horizon
            )
            train = [normalizers[task].normalize(w.train_actions.astype(np.float64)) for task, w in windows.items()]
            try:
                tokenizer.fit(torch.as_tensor(np.concatenate(train), dtype=torch.float32))
            except ValueError as error:
                fail(f"tokenizer.kind={config.kind}: {one_line(error)}")
            trained_with = normalizers
        else:
            try:
                artifact, reference = fetch_registered_tokenizer(tracking_uri(params), config.source, Path(download))
            except (LookupError, TokenizerMismatchError, NonFiniteTokenizerError) as error:
                fail(str(error))
            refuse_unfit(artifact, params)
            tokenizer, trained_with, files_from = artifact.tokenizer, artifact.action_normalizers, artifact.directory
            run.set_tags({"carp.tokenizer_version": reference.version})
        held_out = {task: w.valid_actions if len(w.valid_actions) else w.train_actions for task, w in windows.items()}
        buffer = windows[tasks[0]].buffer
        episode = int(np.flatnonzero(buffer.valid_episodes)[0]) if buffer.valid_episodes.any() else 0
        figure = TOKENIZER_REPORT_DIR / "reconstruction.png"
        names = params.action_format.dimension_names
        metrics, timings = evaluate_kind(
            tokenizer, held_out, normalizers, (tasks[0], buffer.episode(episode)[1]), figure, names
        )
        try:
            sha256 = save_kind_artifact(
                TOKENIZER_DIR, tokenizer, trained_with, params.action_space, metrics, files_from=files_from
            )
        except NonFiniteTokenizerError as error:
            figure.unlink(missing_ok=True)
            fail(str(error))
        run.log_metrics({key.replace("/", "."): value for key, value in {**metrics, **timings}.items()})
        run.log_artifact(figure)
        run.set_tags({"carp.tokenizer_sha256": sha256})
    write_json(TOKENIZER_REPORT_DIR / "metrics.json", metrics)
    write_history(TOKENIZER_REPORT_DIR / "history.csv", [])
    action = "fitted on" if config.source == "pipeline" else f"fetched {config.source}, fitted on"
    summary = summary_line(metrics, dimension_names(tokenizer.action_dim, names))
    print(
        f"{config.kind} tokenizer {action} {list(trained_with)}: {summary}, {metrics['tokens_per_chunk/mean']:.1f} "
        f"tokens per chunk, V={tokenizer.vocabulary_size} on {tasks}; sha256 {sha256[:12]}"
    )


if __name__ == "__main__":
    main()
