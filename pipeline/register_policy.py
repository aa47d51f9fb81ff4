"""register_policy stage: the policy evaluate confirmed -> MLflow Model Registry + models/policy_ref/<task>/<policy>/.

For a family listed in `register`, registers the checkpoint that evaluate ran on the test seeds (the candidate its
summary reports/eval/<task>/<policy>/seed<seed>.json names under eval.selection, or the average it rebuilt) as
carp-policy-<task>-<policy>, tagged with that evaluation, points `<tracking.policy_alias>-seed<seed>` at it, and
`tracking.policy_alias` itself for the first of `seeds`. The same bytes keep their version. Writes the reference of
the seed's alias to models/policy_ref/<task>/<policy>/seed<seed>.json.
"""

import pandas as pd
from stage_support import (
    evaluation_report,
    fail,
    mlflow_stage,
    policy_dir,
    policy_reference,
    policy_report_dir,
    policy_stage_args,
    setup_logging,
    tracking_uri,
)

from carp.tracking.registry import policy_aliases, register_confirmed_policy


def main() -> None:
    setup_logging()
    args, params = policy_stage_args(__doc__)
    if args.multitask or args.policy not in params.register:
        listed = f"--policy {args.policy}{' --multitask' if args.multitask else ''}"
        fail(f"{args.params}: register={list(params.register)}: {listed} is not listed")
    history = policy_report_dir(args.task, args.policy, args.seed) / "history.csv"
    aliases = policy_aliases(params.tracking.policy_alias, args.seed, params.seeds)
    tags = {"carp.policy_type": args.policy, "carp.training_seed": str(args.seed)}
    try:
        epoch_losses = pd.read_csv(history)["loss"].tolist()
        with mlflow_stage(params, f"register_policy@{args.task}-{args.policy}-{args.seed}", args.task, tags):
            reference = register_confirmed_policy(
                tracking_uri(params),
                policy_dir(args.task, args.policy, args.seed),
                epoch_losses,
                evaluation_report(args.task, args.policy, args.seed),
                aliases,
            )
    except (FileNotFoundError, ValueError) as error:
        fail(str(error))
    output = policy_reference(args.task, args.policy, args.seed)
    output.parent.mkdir(parents=True, exist_ok=True)
    reference.save(output)
    print(
        f"{args.task} {args.policy} seed {args.seed}: {reference.name} version {reference.version} "
        f"(sha256 {reference.sha256[:12]}) at @{', @'.join(aliases)}"
    )


if __name__ == "__main__":
    main()
