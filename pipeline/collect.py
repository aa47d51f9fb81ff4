"""collect stage: scripted-expert demos (or the user's own robomimic file or LeRobotDataset) -> data/raw/<task>.hdf5."""

import json

from stage_support import PROJECT_DIR, STAGING_DIR, fail, load, mlflow_stage, parse_args, setup_logging

from carp.data.demo_sources import import_demos
from carp.data.robomimic_io import DatasetError
from carp.tasks.base import lerobot_adapter


def main() -> None:
    setup_logging()
    args = parse_args(__doc__, per_task=True)
    params = load(args.params)
    if args.task not in params.tasks:
        fail(f"{args.params}: tasks={list(params.tasks)}: --task {args.task} is not listed")
    task = params.task(args.task)
    output = PROJECT_DIR / "data" / "raw" / f"{args.task}.hdf5"
    user_file = params.data.raw_files.get(args.task)
    if user_file:
        source = (PROJECT_DIR / user_file).resolve()
        try:
            # The same checks as ingest (low-dim obs keys, action width, filter mask), so a file ingest would refuse
            # is refused here, before anything is written at the output. An image run reads the proprioception
            # only: a camera file need not hold the object's pose. A LeRobotDataset that records no env_args takes
            # the task's own (a task without a simulator: the description of the dataset's actions and observations).
            # A task may derive obs keys a LeRobotDataset lacks from its other features (Push-T: from
            # lerobot/pusht_keypoints' T vertices).
            demos = import_demos(
                source,
                output,
                params.obs_keys_for(args.task),
                action_dim=params.action_format.stored_dim,
                filter_key=params.data.filter_key,
                staging_dir=STAGING_DIR,
                env_name=task.env_name,
                env_args=lambda: task.make_env_args(params.data.controller),
                cameras=params.data.cameras if params.data.image_keys else (),
                image_size=params.data.image_size,
                adapter=lerobot_adapter(task),
            )
        except DatasetError as error:
            fail(str(error))
        except OSError as error:
            fail(f"{source}: cannot write {output} ({error.strerror or error})")
        with mlflow_stage(params, f"collect@{args.task}", args.task) as run:
            run.log_metrics({"demos": len(demos.episodes)})
        print(f"{args.task}: copied {len(demos.episodes)} demos from {source}")
        return

    with mlflow_stage(params, f"collect@{args.task}", args.task) as run:
        from carp.data.collect import CollectionError, collect_demonstrations

        try:
            summary = collect_demonstrations(
                task=args.task,
                num_demos=params.data.demos_for(args.task),
                output_path=output,
                seed=params.data.collection_seed,
                controller=params.data.controller,
                max_steps=params.data.collection_max_steps,
                staging_dir=STAGING_DIR,
            )
        except CollectionError as error:
            fail(str(error))
        run.log_metrics(
            {
                "expert_success_rate": summary.success_rate,
                "demos": summary.kept,
                "attempts": summary.attempted,
                "seconds": summary.seconds,
            }
        )
        print(
            f"{args.task}: expert succeeded on {summary.kept}/{summary.attempted} seeded episodes "
            f"({100 * summary.success_rate:.1f}%), {summary.seconds:.1f} s -> {output.relative_to(PROJECT_DIR)}"
        )
        print(json.dumps({"task": args.task, "success_rate": summary.success_rate}))


if __name__ == "__main__":
    main()
