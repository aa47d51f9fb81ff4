"""Optuna sweep over scale schedules and codebook sizes; every trial is a `dvc exp run` in this workspace.

    python pipeline/sweep.py [--trials N] [--params params.yaml]

Reads the `sweep` section (and `tasks`, `policies`, `seeds`, `eval`, `comparison`) of the params file, runs trials
one at a time until the budget (`sweep.num_trials`, or --trials) counts that many finished trials in the study's
storage, then confirms the best one on the test seeds, and writes reports/sweep/trials.csv and
reports/sweep/best_params.txt. Killed or interrupted, it resumes where it stopped. Each trial first sets its values
in params.yaml and reproduces only `train_tokenizer` (for the pruning check), then runs `dvc exp run -n
sweep-<study>-t<number> -S scales=... -S codebook_size=... -S eval.run_test=false ... evaluate`: validation
episodes only (`sweep.validation_episodes` per candidate), pruned by `sweep.pruner` as they come in. The
confirmation trains the best trial's settings and the default ones on `sweep.confirm_seeds` (none of the trials'
`seeds`: new networks, not the ones the trials chose) as two more experiments and compares them on the test seeds.
Experiments are pushed to `sweep.git_remote` when one is set. The workspace is left holding the last experiment's
params and outputs.

The default settings (`scales`, `codebook_size`) and the trials' training seeds (`seeds`) are the committed
params.yaml's (HEAD, the experiments' baseline): every experiment leaves its own values of them in the workspace's
params.yaml, so after a first trial (a resumed sweep, a second study) that file no longer holds them.

Several workers: start this same command in several workspaces (clones of one commit, on any machines) whose
`sweep.storage` names one PostgreSQL database; they share the study, each grid point runs once, and the budget
holds across them (docs/several-machines.md). One sweep at a time per workspace.
"""

import argparse
import dataclasses
import fcntl
import logging
import os
import socket
import subprocess
import tempfile
from pathlib import Path

from stage_support import (
    PROJECT_DIR,
    REPORTS_DIR,
    TOKENIZER_REPORT_DIR,
    evaluation_report,
    fail,
    git_commit,
    load,
    project_root,
    setup_logging,
    tracking_uri,
)

from carp.config import ConfigError, Params, load_params
from carp.sweep.confirmation import ConfirmationPlan
from carp.sweep.dvc_runner import DvcExperimentRunner
from carp.sweep.space import TrialSettings
from carp.sweep.study import ExperimentFailedError, SweepStateError, run_sweep
from carp.sweep.tracking import SweepTracker
from carp.tasks.base import ROLLOUTS
from carp.tracking.runs import resolve_tracking_uri

logger = logging.getLogger(__name__)

BASELINE_KEYS = ("scales", "codebook_size", "seeds")
"""Params that every sweep experiment sets (``-S``) and leaves in the workspace, so they are read from HEAD."""


def _hold_workspace_lock() -> object:
    """Lock the workspace for this sweep (released when the process exits); fail if another sweep holds it.

    Workers share a study, not a workspace: each trial rewrites params.yaml and the outputs in place.
    """
    path = PROJECT_DIR / ".dvc" / "tmp" / "sweep.lock"
    path.parent.mkdir(parents=True, exist_ok=True)
    handle = path.open("w")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        fail(f"{path}: another sweep is running in this workspace; start each sweep worker in its own clone")
    return handle


def _with_committed_baseline(params: Params) -> Params:
    """`params` with the committed params.yaml's :data:`BASELINE_KEYS` (see the module docstring)."""
    shown = subprocess.run(
        ["git", "show", "HEAD:params.yaml"], cwd=PROJECT_DIR, capture_output=True, text=True, check=False
    )
    if shown.returncode != 0:
        fail(f"params.yaml is not committed ({shown.stderr.strip()}); commit it: the sweep's experiments start there")
    with tempfile.TemporaryDirectory(prefix="carp-sweep-") as directory:
        committed_path = Path(directory) / "params.yaml"
        committed_path.write_text(shown.stdout)
        try:
            committed = load_params(committed_path)
        except ConfigError as error:
            fail(f"params.yaml at HEAD{str(error).removeprefix(str(committed_path))}")
    changed = [key for key in BASELINE_KEYS if getattr(params, key) != getattr(committed, key)]
    if changed:
        logger.info(
            "params.yaml: %s differ from the committed file's (an earlier experiment's, or not committed); "
            "the default settings and the trials' training seeds are the committed ones",
            ", ".join(changed),
        )
    return dataclasses.replace(params, **{key: getattr(committed, key) for key in BASELINE_KEYS})


def _check_experiment_params(params: Params, runner: DvcExperimentRunner, path: Path) -> None:
    """Fail now, not in every trial's first stage, when the experiments' ``eval`` settings break a constraint."""
    for settings in (runner.trial_eval_settings(), runner.confirmation_eval_settings()):
        try:
            dataclasses.replace(params, eval=dataclasses.replace(params.eval, **settings))
        except ConfigError as error:
            fail(f"{path}: with the sweep's evaluation settings {settings} (sweep.validation_episodes): {error}")


def main() -> None:
    setup_logging()
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--params", type=Path, default=PROJECT_DIR / "params.yaml")
    parser.add_argument("--trials", type=int, default=None, help="total trial budget (default: sweep.num_trials)")
    args = parser.parse_args()
    params = _with_committed_baseline(load(args.params))
    if args.trials is not None and args.trials < 1:
        fail(f"--trials={args.trials}: must be at least 1")
    if project_root() != PROJECT_DIR:
        fail("run the sweep in the project workspace, not inside a DVC temporary workspace")
    if not params.policies:
        fail(f"{args.params}: policies=[]: the sweep trains and evaluates single-task policies; list a family")
    offline = [task for task in params.tasks if params.task(task).evaluation != ROLLOUTS]
    if offline:
        fail(f"{args.params}: tasks={list(params.tasks)}: {offline} have no simulator; the sweep scores rollouts")
    reused = sorted(set(params.sweep.confirm_seeds) & set(params.seeds))
    if reused:
        # The winner's trial networks were selected for their validation score: the confirmation trains new ones.
        fail(
            f"{args.params}: sweep.confirm_seeds={list(params.sweep.confirm_seeds)}: must not include the trials' "
            f"training seeds seeds={list(params.seeds)} (both hold {reused})"
        )
    lock = _hold_workspace_lock()
    config = dataclasses.replace(
        params.sweep,
        storage=resolve_tracking_uri(params.sweep.storage, project_root()),
        num_trials=args.trials or params.sweep.num_trials,
    )
    tracker = SweepTracker(
        tracking_uri(params),
        experiment_name=f"{params.tracking.experiment_prefix}-sweep",
        tags={"carp.git_commit": git_commit()},
    )
    runner = DvcExperimentRunner(
        PROJECT_DIR,
        TOKENIZER_REPORT_DIR / "metrics.json",
        evaluation_report,
        params.tasks,
        params.policies,
        params.seeds,
        config.git_remote,
        os.environ,
        config.validation_episodes,
    )
    _check_experiment_params(params, runner, args.params)
    plan = ConfirmationPlan(
        default=TrialSettings(tuple(params.scales), params.codebook_size),
        seeds=tuple(config.confirm_seeds),
        margin=params.comparison.margin,
        alpha=params.comparison.alpha,
        worker=f"{socket.gethostname()}:{PROJECT_DIR}",
        min_seeds=params.comparison.min_seeds,
    )
    try:
        result = run_sweep(config, runner, REPORTS_DIR / "sweep", tracker, plan)
    except (SweepStateError, ExperimentFailedError) as error:
        fail(str(error))
    finally:
        lock.close()
    print("\n".join(result.summary_lines(config)))
    print(f"wrote {(REPORTS_DIR / 'sweep').relative_to(PROJECT_DIR)}/trials.csv and best_params.txt")


if __name__ == "__main__":
    main()
