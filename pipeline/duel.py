"""Two evaluated policies of a task, run in rounds on shared test seeds until an anytime-valid test decides.

    python pipeline/duel.py --task can --first carp --second diffusion_unet [--seed 0] [--episodes 500]

Each side is a family of `policies` or a family's multi-task policy (`<family>-multitask`), at training seed --seed,
on the checkpoint its evaluate stage confirmed on the test seeds. The duel takes the test seeds from eval.seed on, up
to --episodes (default eval.episodes; more extends the test range, which must stay clear of the validation seeds):
the episodes the evaluate stages already ran on those seeds count as the first round, and each further round runs
--round-episodes new seeds on both policies. After every round the sequential McNemar test
(`carp.evaluation.sequential`) decides or goes on. Writes reports/duel/<task>/<first>_vs_<second>/seed<k>/: each
side's episodes (<label>_episodes.csv, appended after each round, so a killed duel resumes where it stopped) and
verdict.json. Not a DVC stage: it adds episodes beside what the pipeline evaluated and changes none of its outputs.

A duel compares two trained networks (one training seed of each family), never the families: its verdict names
them by seed. The duels behind one report share its error rate: --duels N splits alpha over them (Bonferroni), and
the verdict records N.
"""

import argparse
import dataclasses
import json
import tempfile
from pathlib import Path

import pandas as pd
from evaluation_support import episode_runner
from stage_support import (
    PROCESSED_DIR,
    PROJECT_DIR,
    REPORTS_DIR,
    evaluation_report,
    fail,
    load,
    policy_paths,
    seed_name,
    setup_logging,
)

from carp.config import ConfigError, Params
from carp.data.dataset import load_task_windows
from carp.evaluation.runner import episodes_table
from carp.evaluation.selection import confirmed_checkpoint, find_candidates
from carp.evaluation.sequential import run_duel
from carp.outputs import MULTITASK_SUFFIX, write_json
from carp.tasks.base import ROLLOUTS

DUEL_DIR = REPORTS_DIR / "duel"


@dataclasses.dataclass(frozen=True)
class Side:
    """One policy of the duel: its label, family, checkpoint directory, training history and evaluation."""

    label: str
    family: str
    run_dir: Path
    history: Path
    summary: dict
    episodes: pd.DataFrame


def main() -> None:
    setup_logging()
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--params", type=Path, default=PROJECT_DIR / "params.yaml")
    parser.add_argument("--task", required=True)
    parser.add_argument("--first", required=True, help="a family of `policies`, or <family>-multitask")
    parser.add_argument("--second", required=True, help="a family of `policies`, or <family>-multitask")
    parser.add_argument("--seed", type=int, default=None, help="training seed (default: the first of `seeds`)")
    parser.add_argument("--episodes", type=int, default=None, help="most paired episodes (default: eval.episodes)")
    parser.add_argument("--round-episodes", type=int, default=20, help="new seeds per round; >= 1")
    parser.add_argument("--alpha", type=float, default=None, help="false-positive rate (default: comparison.alpha)")
    parser.add_argument(
        "--duels", type=int, default=1, help="duels reported together; each runs at alpha / duels (default 1)"
    )
    args = parser.parse_args()
    params = load(args.params)
    seed = params.seeds[0] if args.seed is None else args.seed
    if args.task not in params.tasks:
        fail(f"{args.params}: tasks={list(params.tasks)}: --task {args.task} is not listed")
    if params.task(args.task).evaluation != ROLLOUTS:
        fail(
            f"{args.params}: tasks={list(params.tasks)}: {args.task} has no simulator, and a duel rolls policies out "
            "(the report compares its families offline)"
        )
    if seed not in params.seeds:
        fail(f"{args.params}: seeds={list(params.seeds)}: --seed {seed} is not listed")
    if args.first == args.second:
        fail(f"--first and --second name the same policy, {args.first}")
    if args.round_episodes < 1:
        fail(f"--round-episodes {args.round_episodes}: must be >= 1")
    alpha = params.comparison.alpha if args.alpha is None else args.alpha
    if not 0 < alpha < 1:
        fail(f"--alpha {alpha}: must be in (0, 1)")
    if args.duels < 1:
        fail(f"--duels {args.duels}: must be >= 1")
    try:
        # The whole params are checked again, so an extended test range must stay clear of the collection and
        # validation seeds.
        extended = dataclasses.replace(params.eval, episodes=args.episodes or params.eval.episodes)
        seeds = dataclasses.replace(params, eval=extended).eval.test_seeds()
    except ConfigError as error:
        fail(f"--episodes {args.episodes}: {error}")
    sides = [side_of(params, args.params, args.task, label, seed) for label in (args.first, args.second)]
    out_dir = DUEL_DIR / args.task / f"{args.first}_vs_{args.second}" / seed_name(seed)
    files = [out_dir / f"{side.label}_episodes.csv" for side in sides]
    done = episodes_so_far(files, [side.episodes for side in sides], seeds)
    windows = load_task_windows(
        PROCESSED_DIR / args.task, params.data.action_horizon, params.data.obs_steps, params.data.action_steps
    )
    runners = [episode_runner(params, args.task, side.family, windows.buffer.attrs["env_args"]) for side in sides]
    with tempfile.TemporaryDirectory(prefix="carp-duel-") as scratch:
        checkpoints = []
        for index, side in enumerate(sides):
            try:
                candidates = find_candidates(side.run_dir, pd.read_csv(side.history)["loss"].tolist())
                (Path(scratch) / str(index)).mkdir()
                checkpoints.append(confirmed_checkpoint(candidates, side.summary, Path(scratch) / str(index)))
            except (OSError, ValueError) as error:
                fail(f"{evaluation_report(args.task, side.label, seed)}: {error}")
        out_dir.mkdir(parents=True, exist_ok=True)
        for file, episodes in zip(files, done):
            episodes.to_csv(file, index=False)

        def run_round(round_seeds: list[int]) -> tuple[list[bool], list[bool]]:
            tables = [episodes_table(run(checkpoint, round_seeds)[1]) for run, checkpoint in zip(runners, checkpoints)]
            # Both sides of a round are written after both ran, in the columns their files began with.
            for file, table, kept in zip(files, tables, done):
                table.reindex(columns=kept.columns).to_csv(file, mode="a", header=False, index=False)
            first, second = (table["success"].astype(bool).tolist() for table in tables)
            return first, second

        verdict, _, _ = run_duel(
            f"{args.first} (training seed {seed})",
            f"{args.second} (training seed {seed})",
            run_round,
            seeds,
            args.round_episodes,
            alpha / args.duels,
            done=(done[0]["success"].astype(bool).tolist(), done[1]["success"].astype(bool).tolist()),
        )
    scope = {"task": args.task, "training_seed": seed, "duels": args.duels, "family_alpha": alpha}
    write_json(out_dir / "verdict.json", dataclasses.asdict(verdict) | scope)
    print(
        f"{args.task}: {verdict.explanation} This compares two trained networks, not the families; alpha {alpha:g} "
        f"split over {args.duels} duel(s)."
    )


def side_of(params: Params, params_path: Path, task: str, label: str, seed: int) -> Side:
    """The duel side named `label` (a family, or `<family>-multitask`); one error line when it was not evaluated."""
    multitask = label.endswith(MULTITASK_SUFFIX)
    family = label.removesuffix(MULTITASK_SUFFIX)
    key, listed = ("multitask", params.multitask) if multitask else ("policies", params.policies)
    if family not in listed:
        fail(f"{params_path}: {key}={list(listed)}: {label} is not listed")
    run_dir, report_dir, _ = policy_paths(task, family, seed, multitask)
    summary = evaluation_report(task, label, seed)
    episodes = summary.with_name(f"{summary.stem}_episodes.csv")
    if not summary.exists() or not episodes.exists():
        fail(f"{summary}: no evaluation of {label} on {task} at training seed {seed} (run its evaluate stage first)")
    return Side(
        label, family, run_dir, report_dir / "history.csv", json.loads(summary.read_text()), pd.read_csv(episodes)
    )


def episodes_so_far(files: list[Path], evaluated: list[pd.DataFrame], seeds: list[int]) -> list[pd.DataFrame]:
    """Each side's episodes on the first of `seeds`, in seed order and of one length.

    A duel that ran before resumes from its files (cut to the rounds both sides finished); a new one starts from the
    episodes the evaluate stages ran on the longest run of leading seeds that both sides have.
    """
    if all(file.exists() for file in files):
        tables = [pd.read_csv(file) for file in files]
        count = min(len(table) for table in tables)
        if all(table["seed"].head(count).tolist() == seeds[:count] for table in tables):
            return [table.head(count) for table in tables]
    by_seed = [table.drop_duplicates("seed").set_index("seed", drop=False) for table in evaluated]
    count = 0
    while count < len(seeds) and all(seeds[count] in table.index for table in by_seed):
        count += 1
    return [table.loc[seeds[:count]].reset_index(drop=True) for table in by_seed]


if __name__ == "__main__":
    main()
