"""collect stage: scripted-expert demos (or the user's own robomimic file) -> data/raw/<task>.hdf5."""

import json
import shutil

from stage_support import PROJECT_DIR, fail, load, mlflow_stage, parse_args, setup_logging

from carp.config import TASK_NAMES
from carp.data.robomimic_io import DatasetError, read_demonstrations


def main() -> None:
    setup_logging()
    args = parse_args(__doc__, per_task=True)
    params = load(args.params)
    if args.task not in TASK_NAMES:
        fail(f"--task {args.task!r}: must be one of {TASK_NAMES}")
    output = PROJECT_DIR / "data" / "raw" / f"{args.task}.hdf5"
    user_file = params.data.raw_files.get(args.task)
    with mlflow_stage(params, f"collect@{args.task}", args.task) as run:
        if user_file:
            source = (PROJECT_DIR / user_file).resolve()
            try:
                demos = read_demonstrations(source, params.data.obs_keys, action_dim=7)
            except DatasetError as error:
                fail(str(error))
            temporary = output.with_name(f".{output.name}.tmp")
            output.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source, temporary)
            temporary.replace(output)
            run.log_metrics({"demos": len(demos.episodes)})
            print(f"{args.task}: copied {len(demos.episodes)} demos from {source}")
            return

        from carp.data.collect import CollectionError, collect_demonstrations

        try:
            summary = collect_demonstrations(
                task=args.task,
                num_demos=params.data.demos_for(args.task),
                output_path=output,
                seed=params.data.collection_seed,
                controller=params.data.controller,
                max_steps=params.data.collection_max_steps,
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
