"""ingest stage: data/raw/<task>.hdf5 -> data/processed/<task>/ (zarr replay buffer + normalization stats)."""

import os
from dataclasses import asdict

from stage_support import (
    PROCESSED_DIR,
    PROJECT_DIR,
    RAW_DIR,
    STAGING_DIR,
    camera_settings,
    fail,
    load,
    mlflow_stage,
    parse_args,
    setup_logging,
)

from carp.data.ingest import ingest_demonstrations
from carp.data.rendering import RenderingError
from carp.data.robomimic_io import DatasetError
from carp.data.staging import remove_stale_entries


def main() -> None:
    setup_logging()
    args = parse_args(__doc__, per_task=True)
    params = load(args.params)
    raw = RAW_DIR / f"{args.task}.hdf5"
    output = PROCESSED_DIR / args.task
    # Earlier versions staged next to the output, inside train_tokenizer's dependency data/processed; a killed run's
    # leftover there would stay in that dependency's hash.
    remove_stale_entries(PROCESSED_DIR)
    try:
        # Cameras a file does not store are rendered offscreen, as an image policy's rollouts render them.
        cameras = camera_settings(params)
        summary = ingest_demonstrations(
            raw,
            output,
            obs_keys=params.obs_keys_for(args.task),
            controller=params.data.controller,
            env_name=params.task(args.task).env_name,
            filter_key=params.data.filter_key,
            valid_fraction=params.data.valid_fraction,
            staging_dir=STAGING_DIR,
            camera_settings=cameras,
            render_workers=params.data.render_workers or os.cpu_count() or 1,
            subset_size=params.data.subset_size,
            subset_seed=params.data.subset_seed,
            source_name=str(raw.relative_to(PROJECT_DIR)),
        )
    except (DatasetError, RenderingError) as error:
        fail(str(error))
    with mlflow_stage(params, f"ingest@{args.task}", args.task) as run:
        run.log_metrics({k: v for k, v in asdict(summary).items() if isinstance(v, (int, float))})
    print(
        f"{args.task}: {summary.episodes} episodes ({summary.valid_episodes} held out), {summary.steps} steps, "
        f"obs {summary.obs_dim}-D, actions {summary.action_dim}-D -> {output.relative_to(PROJECT_DIR)}"
    )
    if cameras is not None:
        print(f"{args.task}: images {', '.join(cameras.image_keys)} at {cameras.image_size} px")


if __name__ == "__main__":
    main()
