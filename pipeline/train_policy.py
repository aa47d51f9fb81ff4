"""train_policy stage: a task's processed data + the referenced tokenizer -> models/policy/<task>/<policy>/policy.pt."""

from dataclasses import asdict

import torch
from stage_support import (
    CHECKPOINT_DIR,
    PROCESSED_DIR,
    TOKENIZER_DIR,
    TOKENIZER_REF,
    fail,
    mlflow_stage,
    policy_dir,
    policy_report_dir,
    policy_stage_args,
    select_device,
    setup_logging,
    write_history,
    write_json,
)

from carp.data.dataset import load_task_windows
from carp.evaluation.offline import held_out_action_errors
from carp.policies.context import PolicyContext
from carp.policies.registry import train_policy
from carp.tokenizer.artifact import TokenizerMismatchError, check_compatible, load_tokenizer_artifact
from carp.tracking.registry import TokenizerReference
from carp.training.checkpoint import CheckpointError
from carp.training.loop import PolicyTrainingData
from carp.training.runtime import precision_name, resolve_precision


def main() -> None:
    setup_logging()
    args, params = policy_stage_args(__doc__)
    data = params.data
    reference = TokenizerReference.load(TOKENIZER_REF)
    try:
        # models/tokenizer holds the referenced tokenizer whatever its source (train_tokenizer fetches registered ones).
        artifact = load_tokenizer_artifact(TOKENIZER_DIR, expected_sha256=reference.sha256, recorded_in=TOKENIZER_REF)
        check_compatible(artifact, params.action_space, params.scales, params.codebook_size)
    except (CheckpointError, TokenizerMismatchError, FileNotFoundError) as error:
        fail(str(error))

    windows = load_task_windows(PROCESSED_DIR / args.task, data.action_horizon, data.obs_steps, data.action_steps)
    # The task's own statistics, as the tokenizer saw every training task's actions (carp.tokenizer.artifact).
    obs_normalizer, action_normalizer = windows.obs_normalizer, windows.action_normalizer
    train_data = PolicyTrainingData(
        obs=torch.as_tensor(obs_normalizer.normalize(windows.train_obs), dtype=torch.float32),
        actions=torch.as_tensor(action_normalizer.normalize(windows.train_actions), dtype=torch.float32),
    )
    device = select_device(params)
    precision = precision_name(resolve_precision(params.training.precision, device))
    history: list[dict] = []
    tags = {"carp.tokenizer": reference.uri, "carp.training_precision": precision, "carp.policy_type": args.policy}
    stage = f"train_policy@{args.task}-{args.policy}"
    with mlflow_stage(params, stage, args.task, tags) as run:

        def log_epoch(epoch: int, metrics: dict[str, float]) -> None:
            history.append({"epoch": epoch + 1, **metrics})
            run.log_metrics(metrics, step=epoch + 1)

        context = PolicyContext(
            obs_normalizer=obs_normalizer,
            action_normalizer=action_normalizer,
            obs_steps=data.obs_steps,
            action_horizon=data.action_horizon,
            tokenizer_artifact=artifact,
            metadata={"task": args.task, "tokenizer": asdict(reference), "mlflow_run_id": run.run_id},
        )
        policy = train_policy(
            args.policy,
            params.family_config(args.policy),
            params.training,
            context,
            train_data,
            CHECKPOINT_DIR / "policy" / args.task / args.policy,
            device=device,
            epochs=params.training.epochs_for(args.task),
            on_epoch_end=log_epoch,
        )
        held_out = held_out_action_errors(
            policy, windows.valid_obs, windows.valid_actions, data.obs_steps, data.action_steps
        )
        run.log_metrics(held_out)
        checkpoint = policy_dir(args.task, args.policy) / "policy.pt"
        checkpoint.parent.mkdir(parents=True, exist_ok=True)
        policy.save(checkpoint)
        report_dir = policy_report_dir(args.task, args.policy)
        write_history(report_dir / "history.csv", history)
        last = history[-1]
        final = {f"final_{key}": last[key] for key in ("loss", "token_accuracy") if key in last}
        write_json(report_dir / "metrics.json", {**held_out, **final})
        run.log_artifact(checkpoint, "checkpoint")
    print(
        f"{args.task} {args.policy}: final loss {final['final_loss']:.4f}, held-out action RMSE "
        f"{held_out.get('valid_action_rmse', float('nan')):.4f}"
    )


if __name__ == "__main__":
    main()
