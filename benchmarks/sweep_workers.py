"""Wall time of the sweep over a tiny grid run by 1 and by 2 workers sharing one study in PostgreSQL.

Builds a workspace with the tests' tiny params (``tests/pipeline/workspace.py``: 3 demos, 2 epochs, 2 evaluation
episodes) and ingests its demos once. For each worker count it then copies that workspace once per worker (fresh
DVC run caches, so no trial is restored from an earlier measurement), starts ``python pipeline/sweep.py`` in every
copy at once and times until the last one exits. The workers share a new study in the ``optuna`` database of a
tracking server (PostgreSQL and MLflow) started in a temporary directory with ``tools/tracking_server.py``. The grid
is ``--points`` scale schedules ending at ``l = 4`` with codebook size 8, without pruning, and the budget is the grid.

    .venv/bin/python benchmarks/sweep_workers.py [--workers 1 2] [--points 2]
"""

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import optuna
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from tests.pipeline.workspace import dvc, make_workspace, run, tool_env  # noqa: E402

SCHEDULES = [[1, 4], [1, 2, 4], [4], [2, 4]]
TRACKING_SERVER = REPO / "tools" / "tracking_server.py"


def tool(*arguments: str) -> str:
    """Run ``tools/tracking_server.py`` and return its output; exit with its error when it fails."""
    completed = subprocess.run([sys.executable, str(TRACKING_SERVER), *arguments], capture_output=True, text=True)
    if completed.returncode != 0:
        sys.exit(completed.stdout + completed.stderr)
    return completed.stdout


def configure(template: Path, storage: str, tracking_uri: str, study: str, points: int) -> None:
    """Point the template's sweep at the shared study and the server, and commit."""
    params = yaml.safe_load((template / "params.yaml").read_text())
    params["tracking"]["uri"] = tracking_uri
    params["sweep"].update(
        study_name=study,
        storage=storage,
        num_trials=points,
        scale_schedules=SCHEDULES[:points],
        codebook_sizes=[8],
        prune_factor=1000.0,
        heartbeat_seconds=2,
        pruner="none",
        validation_episodes=1,
        confirm_seeds=[1, 2],
    )
    # The two confirmation seeds are enough for its verdict.
    params["comparison"]["min_seeds"] = 2
    (template / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    for command in (["git", "add", "params.yaml"], ["git", "commit", "-qm", f"study {study}"]):
        if run(command, template).returncode != 0:
            sys.exit(f"{' '.join(command)} failed in {template}")


def measure(template: Path, directory: Path, workers: int, environment: dict) -> float:
    """Seconds from starting ``workers`` sweeps (one per fresh copy of ``template``) until the last one exits."""
    copies = []
    for index in range(workers):
        copy = directory / f"worker-{index}" / "carp"
        shutil.copytree(template, copy, symlinks=True, ignore=shutil.ignore_patterns("mlflow.db", "mlartifacts"))
        copies.append(copy)
    started = time.perf_counter()
    processes = []
    for copy in copies:
        with (copy.parent / "sweep.log").open("w") as log:
            command = [sys.executable, "pipeline/sweep.py"]
            processes.append(subprocess.Popen(command, cwd=copy, env=environment, stdout=log, stderr=subprocess.STDOUT))
    for process, copy in zip(processes, copies):
        if process.wait() != 0:
            sys.exit(f"a sweep worker failed; its log: {copy.parent / 'sweep.log'}")
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--points", type=int, default=2, choices=range(1, len(SCHEDULES) + 1))
    arguments = parser.parse_args()
    if min(arguments.workers) < 1:
        parser.error(f"--workers must each be at least 1, got {arguments.workers}")

    directory = Path(tempfile.mkdtemp(prefix="carp-sweep-bench-"))
    directory.chmod(0o755)  # the database account (PostgreSQL refuses root) must enter it
    server = directory / "server"
    try:
        tool("start", "--dir", str(server), "--port", "0")
        tracking_uri = tool("status", "--dir", str(server)).strip()
        storage = tool("sweep-storage", "--dir", str(server)).strip()
        environment = {**tool_env(), "PGPASSFILE": str(server / "pgpass"), "GOMP_SPINCOUNT": "5000"}
        template = make_workspace(directory / "template" / "carp")
        ingested = run(dvc("repro", "ingest"), template, timeout=3600)
        if ingested.returncode != 0:
            sys.exit(ingested.stderr[-3000:])
        grid = arguments.points
        print(f"sweep over {grid} grid points, budget {grid}; tiny params; {os.cpu_count()} CPUs")
        print(f"{'workers':>7} {'wall s':>7} {'trials':>6} {'points run twice':>16}")
        os.environ["PGPASSFILE"] = environment["PGPASSFILE"]
        for workers in arguments.workers:
            study = f"bench-{workers}-workers-{time.time_ns()}"
            configure(template, storage, tracking_uri, study, arguments.points)
            seconds = measure(template, directory / study, workers, environment)
            trials = optuna.load_study(study_name=study, storage=storage).get_trials()
            points = [(trial.params["scales"], trial.params["codebook_size"]) for trial in trials]
            print(f"{workers:>7} {seconds:>7.1f} {len(trials):>6} {len(points) - len(set(points)):>16}", flush=True)
    finally:
        if (server / "tracking.json").exists():
            subprocess.run([sys.executable, str(TRACKING_SERVER), "stop", "--dir", str(server)], capture_output=True)
        shutil.rmtree(directory, ignore_errors=True)


if __name__ == "__main__":
    main()
