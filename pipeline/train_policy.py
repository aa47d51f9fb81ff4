"""train_policy stage: processed data of a task + the referenced tokenizer -> models/policy/<task>/policy.pt."""

from dataclasses import asdict

import torch
from stage_support import (
    CHECKPOINT_DIR,
    POLICY_DIR,
    POLICY_REPORT_DIR,
    PROCESSED_DIR,
    TOKENIZER_DIR,
    TOKENIZER_REF,
    copy_fields,
    fail,
    load,
    mlflow_stage,
    parse_args,
    select_device,
    setup_logging,
    write_history,
    write_json,
)

from carp.data.dataset import load_task_windows
from carp.evaluation.offline import held_out_action_errors
from carp.policies.carp.policy import CarpPolicy
from carp.policies.carp.spec import PolicySpec
from carp.tokenizer.artifact import TokenizerMismatchError, check_compatible, load_tokenizer_artifact
from carp.tracking.registry import TokenizerReference
from carp.training.checkpoint import CheckpointError
from carp.training.policy_trainer import PolicyTrainingData, PolicyTrainingSettings, train_policy
from carp.training.runtime import precision_name, resolve_precision


def main() -> None:
    setup_logging()
    args = parse_args(__doc__, per_task=True)
    params = load(args.params)
    data, config = params.data, params.policy
    reference = TokenizerReference.load(TOKENIZER_REF)
    try:
        # models/tokenizer holds the referenced tokenizer whatever its source (train_tokenizer fetches registered ones).
        artifact = load_tokenizer_artifact(TOKENIZER_DIR, expected_sha256=reference.sha256, recorded_in=TOKENIZER_REF)
        check_compatible(artifact, params.action_space, params.scales, params.codebook_size)
    except (CheckpointError, TokenizerMismatchError, FileNotFoundError) as error:
        fail(str(error))
    tokenizer = artifact.tokenizer

    windows = load_task_windows(PROCESSED_DIR / args.task, data.action_horizon, data.obs_steps, data.action_steps)
    # The task's own statistics, as the tokenizer saw every training task's actions (carp.tokenizer.artifact).
    obs_normalizer, action_normalizer = windows.obs_normalizer, windows.action_normalizer
    train_data = PolicyTrainingData(
        obs=torch.as_tensor(obs_normalizer.normalize(windows.train_obs), dtype=torch.float32),
        actions=torch.as_tensor(action_normalizer.normalize(windows.train_actions), dtype=torch.float32),
    )
    spec = copy_fields(
        PolicySpec,
        config,
        obs_dim=obs_normalizer.num_features,
        obs_steps=data.obs_steps,
        action_dim=data.action_dim,
        scales=params.scales,
        latent_channels=tokenizer.spec.latent_channels,
        codebook_size=params.codebook_size,
    )
    device = select_device(params)
    settings = copy_fields(PolicyTrainingSettings, config, device=str(device), epochs=config.epochs_for(args.task))
    precision = precision_name(resolve_precision(settings.precision, device))
    history: list[dict] = []
    tags = {"carp.tokenizer": reference.uri, "carp.training_precision": precision}
    with mlflow_stage(params, f"train_policy@{args.task}", args.task, tags) as run:

        def log_epoch(epoch: int, metrics: dict[str, float]) -> None:
            history.append({"epoch": epoch + 1, **metrics})
            run.log_metrics(metrics, step=epoch + 1)

        transformer = train_policy(
            spec, tokenizer, train_data, settings, CHECKPOINT_DIR / "policy" / args.task, on_epoch_end=log_epoch
        )
        metadata = {"task": args.task, "tokenizer": asdict(reference), "mlflow_run_id": run.run_id}
        tokenizer.cpu()
        policy = CarpPolicy(artifact, transformer.cpu(), obs_normalizer, action_normalizer, metadata).eval()
        held_out = held_out_action_errors(
            policy, windows.valid_obs, windows.valid_actions, data.obs_steps, data.action_steps
        )
        run.log_metrics(held_out)
        checkpoint = POLICY_DIR / args.task / "policy.pt"
        checkpoint.parent.mkdir(parents=True, exist_ok=True)
        policy.save(checkpoint)
        report_dir = POLICY_REPORT_DIR / args.task
        report_dir.mkdir(parents=True, exist_ok=True)
        write_history(report_dir / "history.csv", history)
        final = {"final_loss": history[-1]["loss"], "final_token_accuracy": history[-1]["token_accuracy"]}
        write_json(report_dir / "metrics.json", {**held_out, **final})
        run.log_artifact(checkpoint, "checkpoint")
    print(
        f"{args.task}: final loss {final['final_loss']:.4f}, token accuracy {final['final_token_accuracy']:.3f}, "
        f"held-out action RMSE {held_out.get('valid_action_rmse', float('nan')):.4f}"
    )


if __name__ == "__main__":
    main()
