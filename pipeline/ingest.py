"""ingest stage: data/raw/<task>.hdf5 -> data/processed/<task>/ (zarr replay buffer + normalization stats)."""

from dataclasses import asdict

from stage_support import PROJECT_DIR, fail, load, mlflow_stage, parse_args, setup_logging

from carp.data.ingest import ingest_demonstrations
from carp.data.robomimic_io import DatasetError


def main() -> None:
    setup_logging()
    args = parse_args(__doc__, per_task=True)
    params = load(args.params)
    raw = PROJECT_DIR / "data" / "raw" / f"{args.task}.hdf5"
    output = PROJECT_DIR / "data" / "processed" / args.task
    try:
        summary = ingest_demonstrations(
            raw,
            output,
            obs_keys=params.data.obs_keys,
            controller=params.data.controller,
            filter_key=params.data.filter_key,
            valid_fraction=params.data.valid_fraction,
        )
    except DatasetError as error:
        fail(str(error))
    with mlflow_stage(params, f"ingest@{args.task}", args.task) as run:
        run.log_metrics({k: v for k, v in asdict(summary).items() if isinstance(v, (int, float))})
    print(
        f"{args.task}: {summary.episodes} episodes ({summary.valid_episodes} held out), {summary.steps} steps, "
        f"obs {summary.obs_dim}-D, actions {summary.action_dim}-D -> {output.relative_to(PROJECT_DIR)}"
    )


if __name__ == "__main__":
    main()
