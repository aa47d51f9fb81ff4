"""Recompute the verdicts of the stored evaluations under `results/` with the report's own rules.

Each group below is what one README / docs/results.md row compares: the evaluation folders whose families are set
side by side. A folder given as ``(folder, setting)`` has its families labelled ``<family> (<setting>)``, so that one
family trained with two settings (two tokenizers, say) is compared with itself. The verdicts are decided as a
report decides them (the training seed as the unit, one correction over the group's pairs and precision claims), so a
row's published verdict can be checked against its episodes at any time.

    .venv/bin/python tools/results_verdicts.py [--min-seeds 3] [--alpha 0.05] [--margin 0.05]
"""

import argparse
from pathlib import Path

from carp.outputs import MULTITASK_SUFFIX
from carp.reporting.claims import claims_table, precision_tests
from carp.reporting.comparison import decide_report, family_pairs, multitask_pairs
from carp.reporting.runs import merge_runs, referenced_runs, split_multitask

RESULTS = Path(__file__).resolve().parents[1] / "results"
GROUPS = {
    "Square, CARP and DP-C": ["square/eval"],
    "Square data efficiency, 30 demos": [
        "square-data-efficiency-carp/size30",
        "square-data-efficiency-diffusion_unet/size30",
    ],
    "Square data efficiency, 100 demos": [
        "square-data-efficiency-carp/size100",
        "square-data-efficiency-diffusion_unet/size100",
    ],
    "Square data efficiency, 200 demos": ["square/eval"],
    "NutAssembly, CARP and DP-C": ["nut_assembly-carp/eval", "nut_assembly-diffusion_unet/eval"],
    "Four tasks, multi-task and single-task": [
        "four-tasks-carp/eval",
        "four-tasks-carp-multitask/eval",
        "four-tasks-dpc/eval",
        "four-tasks-dpc-multitask/eval",
    ],
    "Lift, VQ-BeT sampled and greedy codes": ["lift-vq_bet/eval"],
    "Can, VQ-BeT and Consistency Policy": ["can-vq_bet/eval", "can-consistency_policy/eval"],
    "Push-T, VQ-BeT, Consistency Policy and DP-T": [
        "pusht-vq_bet/eval",
        "pusht-consistency_policy/eval",
        "pusht-diffusion_transformer/eval",
    ],
    "Push-T, CARP over two tokenizers, 20 epochs": [
        ("pusht-carp-20-epochs/eval", "default tokenizer"),
        ("pusht-carp-replay-tokenizer/eval", "finest replay tokenizer"),
    ],
    "Push-T, next-token over each tokenizer kind, 20 epochs": [
        ("pusht-tokenizers-next_token/carp_msvq/eval", "carp_msvq"),
        ("pusht-tokenizers-next_token/fast/eval", "FAST scale 50"),
        ("pusht-tokenizers-next_token/binning/eval", "binning"),
        ("pusht-tokenizers-next_token/fsq/eval", "FSQ"),
        ("pusht-tokenizers-next_token/bspline/eval", "B-spline"),
        ("pusht-tokenizers-next_token/joint_msvq/eval", "joint MSVQ"),
    ],
}
TASKS = ("lift", "can", "square", "stack", "nut_assembly", "stack_three", "threading", "pusht")


def main() -> None:
    """Print every group's pairs with their verdicts and explanations."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--min-seeds", type=int, default=3)
    parser.add_argument("--alpha", type=float, default=0.05)
    parser.add_argument("--margin", type=float, default=0.05)
    arguments = parser.parse_args()
    for title, folders in GROUPS.items():
        runs: dict = {}
        for entry in folders:
            folder, setting = entry if isinstance(entry, tuple) else (entry, None)
            found = referenced_runs(RESULTS / folder, TASKS)
            if setting is not None:
                found = {
                    task: {f"{label} ({setting})": by_seed for label, by_seed in labels.items()}
                    for task, labels in found.items()
                }
            runs = merge_runs(runs, found, folder)
        single, multi = split_multitask(runs, MULTITASK_SUFFIX)
        groups = [(list(single), family_pairs(single)), (list(multi), multitask_pairs(single, multi, MULTITASK_SUFFIX))]
        single_tests = precision_tests(single, arguments.min_seeds)
        tests = single_tests + precision_tests(multi, arguments.min_seeds)
        decided, tests = decide_report(groups, tests, arguments.margin, arguments.alpha, min_seeds=arguments.min_seeds)
        split = len(single_tests)
        print(f"## {title}")
        for by_task in decided:
            for task, pairs in by_task.items():
                for pair in pairs:
                    rates = f"{100 * pair.first_rate:.1f}% vs {100 * pair.second_rate:.1f}%"
                    print(f"- {task}: {pair.first} vs {pair.second}, {pair.seeds} seed(s), {rates}: {pair.verdict}")
                    print(f"  {pair.explanation}")
        for evaluations, suffix, group_tests in ((single, "", tests[:split]), (multi, MULTITASK_SUFFIX, tests[split:])):
            claims = claims_table(evaluations, {}, group_tests, suffix=suffix)
            for row in claims.itertuples():
                if "precision" in row.claim:
                    print(f"- {row.task}{suffix}: {row.claim}: {row.verdict}")
                    print(f"  {row.evidence}")
        print()


if __name__ == "__main__":
    main()
