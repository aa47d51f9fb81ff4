"""Stage runs logged per second into a tracking store by 1..N processes at once, and how many writes fail.

Each process logs ``--runs`` runs the way a pipeline stage does (`carp.tracking.runs.stage_run`): the default params
flattened (about 90 values), its tags, then ``--steps`` steps of four metrics, all into one experiment shared by
every process. A run whose logging raises counts as failed, with the first line of its error; after the writers
finish, the store is read back and its FINISHED runs counted.

By default it measures a SQLite file in a temporary directory and a PostgreSQL-backed MLflow server started there
with ``tools/tracking_server.py`` (stopped afterwards); ``--uri`` measures an existing store instead.

    .venv/bin/python benchmarks/tracking_writes.py [--processes 1 2 4] [--runs 10] [--steps 5] [--uri URI]
"""

import argparse
import multiprocessing
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from carp.config import flatten_params, load_params
from carp.tracking.runs import ensure_experiment, find_runs, stage_run

REPO = Path(__file__).resolve().parents[1]


def write_runs(uri: str, experiment: str, worker: int, runs: int, steps: int, barrier, results) -> None:
    """Log ``runs`` stage runs, each with ``steps`` metric steps; put (worker, ok, failures, seconds) on ``results``.

    Timing starts when every writer has imported MLflow (``barrier``), so interpreter start-up is not counted.
    """
    params = flatten_params(load_params(REPO / "params.yaml"))
    failures: list[str] = []
    sys.stdout = open(os.devnull, "w")  # MLflow prints a "View run" line per run on a server
    barrier.wait()
    started = time.perf_counter()
    for index in range(runs):
        flat = {**params, "bench.worker": str(worker), "bench.index": str(index)}
        try:
            with stage_run(uri, experiment, f"writer-{worker}", flat, {"carp.dvc_stage": "bench"}) as run:
                for step in range(steps):
                    run.log_metrics({"loss": 1.0 / (step + 1), "lr": 1e-3, "grad_norm": 0.5, "epoch": step}, step=step)
        except Exception as error:  # a failed write is what is being counted, whatever its type
            failures.append(str(error).splitlines()[0][:200])
    results.put((worker, runs - len(failures), failures, time.perf_counter() - started))


def measure(uri: str, processes: int, runs: int, steps: int) -> dict:
    """Run ``processes`` writers at once into a fresh experiment; counts, rate and a read-back check."""
    experiment = f"bench-{processes}-{time.time_ns()}"
    context = multiprocessing.get_context("spawn")
    results, barrier = context.Queue(), context.Barrier(processes)
    workers = [
        context.Process(target=write_runs, args=(uri, experiment, worker, runs, steps, barrier, results))
        for worker in range(processes)
    ]
    for worker in workers:
        worker.start()
    outcomes = [results.get() for _ in workers]
    for worker in workers:
        worker.join()
    wall = max(outcome[3] for outcome in outcomes)
    logged = find_runs(uri, experiment)
    finished = [run for run in logged if run["status"] == "FINISHED"]
    return {
        "processes": processes,
        "ok": sum(outcome[1] for outcome in outcomes),
        "failed": sum(len(outcome[2]) for outcome in outcomes),
        "errors": sorted({message for outcome in outcomes for message in outcome[2]})[:3],
        "finished_in_store": len(finished),
        "runs_per_second": sum(outcome[1] for outcome in outcomes) / wall,
        "wall_seconds": wall,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--processes", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--runs", type=int, default=10, help="runs per process")
    parser.add_argument("--steps", type=int, default=5, help="metric steps per run")
    parser.add_argument("--uri", help="measure this store only")
    arguments = parser.parse_args()

    directory = Path(tempfile.mkdtemp(prefix="carp-tracking-bench-"))
    directory.chmod(0o755)  # the database account (PostgreSQL refuses root) must enter it
    stores = {"given": arguments.uri} if arguments.uri else {}
    server_dir = directory / "server"
    try:
        if not arguments.uri:
            stores["sqlite"] = f"sqlite:///{directory / 'mlflow.db'}"
            script = REPO / "tools" / "tracking_server.py"
            started = subprocess.run(
                [sys.executable, str(script), "start", "--dir", str(server_dir), "--port", "0"],
                capture_output=True,
                text=True,
            )
            if started.returncode != 0:
                sys.exit(started.stderr)
            stores["server"] = next(line.split()[-1] for line in started.stdout.splitlines() if "tracking.uri" in line)
        for uri in stores.values():
            ensure_experiment(uri, "bench-warm-up")  # a new SQLite store's schema is not part of the measurement
        print(f"{'store':8} {'procs':>5} {'ok':>5} {'failed':>6} {'in store':>8} {'runs/s':>7} {'wall s':>7}  errors")
        for name, uri in stores.items():
            for processes in arguments.processes:
                row = measure(uri, processes, arguments.runs, arguments.steps)
                print(
                    f"{name:8} {row['processes']:>5} {row['ok']:>5} {row['failed']:>6} {row['finished_in_store']:>8} "
                    f"{row['runs_per_second']:>7.2f} {row['wall_seconds']:>7.1f}  {'; '.join(row['errors'])}",
                    flush=True,
                )
    finally:
        if (server_dir / "tracking.json").exists():
            script = REPO / "tools" / "tracking_server.py"
            subprocess.run([sys.executable, str(script), "stop", "--dir", str(server_dir)], check=False)
        shutil.rmtree(directory, ignore_errors=True)


if __name__ == "__main__":
    main()
