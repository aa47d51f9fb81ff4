"""evaluate stage: models/policy/<task>/ -> reports/eval/<task>.json, <task>_episodes.csv (+ GIF videos)."""

import os

from stage_support import (
    EVAL_REPORT_DIR,
    POLICY_DIR,
    PROCESSED_DIR,
    fail,
    load,
    mlflow_stage,
    parse_args,
    setup_logging,
    write_json,
)

from carp.data.dataset import load_task_windows
from carp.evaluation.runner import batched_latency, episodes_table, evaluate_policy, save_gif
from carp.policies.registry import load_policy
from carp.training.checkpoint import CheckpointError


def main() -> None:
    setup_logging()
    args = parse_args(__doc__, per_task=True)
    params = load(args.params)
    data, config = params.data, params.eval
    if config.video:
        # Headless offscreen rendering through EGL (Debian: libegl1, libegl-mesa0, libgl1-mesa-dri; `make render-deps`).
        # Worker processes are spawned after this point and inherit it.
        os.environ.setdefault("MUJOCO_GL", "egl")
    checkpoint = POLICY_DIR / args.task / "policy.pt"
    try:
        policy = load_policy(checkpoint)
    except (CheckpointError, FileNotFoundError) as error:
        fail(str(error))
    windows = load_task_windows(PROCESSED_DIR / args.task, data.action_horizon, data.obs_steps, data.action_steps)
    seeds = [config.seed + index for index in range(config.episodes)]
    workers = config.workers or os.cpu_count() or 1
    top_k = params.policy.top_k_for(args.task)
    with mlflow_stage(
        params, f"evaluate@{args.task}", args.task, {"carp.policy_run_id": policy.metadata.get("mlflow_run_id", "")}
    ) as run:
        summary, results = evaluate_policy(
            checkpoint,
            env_args=windows.buffer.attrs["env_args"],
            controller=data.controller,
            obs_keys=data.obs_keys,
            obs_steps=data.obs_steps,
            action_steps=data.action_steps,
            seeds=seeds,
            max_steps=config.max_steps[args.task],
            workers=min(workers, len(seeds)),
            inference={"top_k": top_k},
            video_episodes=config.video_episodes if config.video else 0,
            backend=config.backend,
        )
        summary.update(batched_latency(policy, windows.valid_obs if len(windows.valid_obs) else windows.train_obs))
        write_json(EVAL_REPORT_DIR / f"{args.task}.json", summary)
        table = episodes_table(results)
        table.to_csv(EVAL_REPORT_DIR / f"{args.task}_episodes.csv", index=False)
        run.log_metrics(summary)
        run.log_artifact(EVAL_REPORT_DIR / f"{args.task}_episodes.csv")
        for result in results:
            if result.frames:
                run.log_artifact(
                    save_gif(result.frames, EVAL_REPORT_DIR / "videos" / f"{args.task}_seed{result.seed}.gif")
                )
    print(
        f"{args.task}: success {summary['successes']}/{summary['episodes']} "
        f"({100 * summary['success_rate']:.1f}%, 95% CI {100 * summary['success_rate_ci_low']:.1f}-"
        f"{100 * summary['success_rate_ci_high']:.1f}%), latency per chunk "
        f"{summary['latency_predict_ms_median']:.2f} ms predict + {summary['latency_decode_ms_median']:.2f} ms decode"
    )


if __name__ == "__main__":
    main()
