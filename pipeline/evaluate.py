"""evaluate stage: models/policy/<task>/<policy>/ -> reports/eval/<task>/<policy>.json, <policy>_episodes.csv."""

import os

from stage_support import (
    EVAL_VIDEO_DIR,
    PROCESSED_DIR,
    camera_settings,
    evaluation_report,
    fail,
    mlflow_stage,
    policy_dir,
    policy_stage_args,
    setup_logging,
)

from carp.data.dataset import load_task_windows
from carp.evaluation.runner import buffer_latency, episodes_table, evaluate_policy, write_episode_videos
from carp.outputs import write_json
from carp.policies.registry import load_policy
from carp.training.checkpoint import CheckpointError


def main() -> None:
    setup_logging()
    args, params = policy_stage_args(__doc__)
    data, config = params.data, params.eval
    if config.video:
        # Headless offscreen rendering through EGL (Debian: libegl1, libegl-mesa0, libgl1-mesa-dri; `make render-deps`).
        # Worker processes are spawned after this point and inherit it.
        os.environ.setdefault("MUJOCO_GL", "egl")
    cameras = camera_settings(params)
    checkpoint = policy_dir(args.task, args.policy) / "policy.pt"
    try:
        policy = load_policy(checkpoint)
    except (CheckpointError, FileNotFoundError) as error:
        fail(str(error))
    windows = load_task_windows(PROCESSED_DIR / args.task, data.action_horizon, data.obs_steps, data.action_steps)
    seeds = [config.seed + index for index in range(config.episodes)]
    workers = config.workers or os.cpu_count() or 1
    inference = params.inference_settings(args.policy, args.task)
    tags = {"carp.policy_run_id": policy.metadata.get("mlflow_run_id", ""), "carp.policy_type": args.policy}
    with mlflow_stage(params, f"evaluate@{args.task}-{args.policy}", args.task, tags) as run:
        summary, results = evaluate_policy(
            checkpoint,
            env_args=windows.buffer.attrs["env_args"],
            controller=data.controller,
            obs_keys=data.low_dim_keys,
            obs_steps=data.obs_steps,
            action_steps=data.action_steps,
            seeds=seeds,
            max_steps=config.max_steps[args.task],
            workers=min(workers, len(seeds)),
            inference=inference,
            video_episodes=config.video_episodes if config.video else 0,
            backend=config.backend,
            cameras=cameras,
        )
        policy.configure_inference(**inference)
        summary.update(
            buffer_latency(
                policy,
                windows,
                PROCESSED_DIR / args.task,
                data.action_horizon,
                data.obs_steps,
                data.action_steps,
                with_images=cameras is not None,
            )
        )
        report = evaluation_report(args.task, args.policy)
        write_json(report, summary)
        episodes = report.with_name(f"{args.policy}_episodes.csv")
        episodes_table(results).to_csv(episodes, index=False)
        run.log_metrics(summary)
        run.log_artifact(episodes)
        for video in write_episode_videos(results, EVAL_VIDEO_DIR, f"{args.task}_{args.policy}"):
            run.log_artifact(video)
    print(
        f"{args.task} {args.policy} ({summary['backend']}): success {summary['successes']}/{summary['episodes']} "
        f"({100 * summary['success_rate']:.1f}%, 95% CI {100 * summary['success_rate_ci_low']:.1f}-"
        f"{100 * summary['success_rate_ci_high']:.1f}%), latency per chunk "
        f"{summary['latency_predict_ms_median']:.2f} ms predict + {summary['latency_decode_ms_median']:.2f} ms decode"
    )


if __name__ == "__main__":
    main()
