"""A temporary copy of the repository with tiny params, for end-to-end `dvc repro` / `dvc exp run` tests."""

import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[2]

TINY_PARAMS = {
    "scales": [1, 2, 4],
    "codebook_size": 16,
    "data": {"num_demos": 3},
    "tokenizer": {"epochs": 2, "batch_size": 64, "checkpoint_every": 1},
    "training": {"epochs": 2, "batch_size": 64},
    "carp": {"depth": 1, "width": 16, "num_heads": 2, "warmup_steps": 2},
    "vq_bet": {
        "vq_training_steps": 20,
        "vq_batch_size": 32,
        "latent_width": 16,
        "encoder_hidden_width": 16,
        "depth": 1,
        "num_heads": 2,
        "width": 16,
        "output_width": 16,
        "head_hidden_width": 32,
    },
    # One worker runs the episodes in the stage's own process: spawning simulator workers (each importing torch and
    # robosuite) costs far more than two short episodes. tests/evaluation and test_kill_and_resume cover workers.
    "eval": {"episodes": 2, "workers": 1, "max_steps": {"lift": 40, "can": 40, "square": 40}},
}


def merge(base: dict, override: dict) -> dict:
    """``base`` with ``override``'s keys replaced, recursing into nested mappings."""
    merged = dict(base)
    for key, value in override.items():
        merged[key] = merge(base[key], value) if isinstance(value, dict) and key in base else value
    return merged


def run(command: list[str], cwd: Path, timeout: float = 900, **kwargs) -> subprocess.CompletedProcess:
    """Run a command with this interpreter's bin directory first on PATH (stage commands call `python`)."""
    return subprocess.run(command, cwd=cwd, env=tool_env(), capture_output=True, text=True, timeout=timeout, **kwargs)


def tool_env() -> dict[str, str]:
    """Environment whose PATH starts with the running interpreter's bin directory."""
    return {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}


def dvc(*arguments: str) -> list[str]:
    """A `dvc` command line run by this interpreter."""
    return [sys.executable, "-m", "dvc", *arguments]


def make_workspace(directory: Path, params: dict | None = None) -> Path:
    """Copy the repository's source files (not data, models or reports) into ``directory`` as a fresh git repo.

    Args:
        directory: created; becomes the workspace root.
        params: overrides merged into ``params.yaml`` on top of :data:`TINY_PARAMS`.
    """
    tracked = subprocess.run(
        ["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO, capture_output=True, text=True, check=True
    )
    for name in tracked.stdout.split():
        source = REPO / name
        if source.is_file() and not name.startswith(("data/", "models/", "reports/")):
            (directory / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, directory / name)
    original = yaml.safe_load((directory / "params.yaml").read_text())
    merged = merge(merge(original, TINY_PARAMS), params or {})
    (directory / "params.yaml").write_text(yaml.safe_dump(merged, sort_keys=False))
    # `dvc exp run` commits experiments too, so the identity goes into the repository's own config.
    for command in (
        ["git", "init", "-q"],
        ["git", "config", "user.name", "carp-test"],
        ["git", "config", "user.email", "carp-test@localhost"],
        ["git", "add", "-A"],
        ["git", "commit", "-qm", "tiny"],
    ):
        completed = run(command, directory)
        assert completed.returncode == 0, completed.stderr
    return directory


def stages_run(dvc_stdout: str) -> set[str]:
    """Names of the stages a `dvc repro` / `dvc exp run` ran, from its "Running stage 'name':" lines."""
    return set(re.findall(r"Running stage '([^']+)'", dvc_stdout))


def queue_status(workspace: Path) -> tuple[dict[str, int], int]:
    """Counts of queued experiments by status (``{"Queued": 1, "Running": 1, ...}``) and of live queue workers."""
    shown = run(dvc("queue", "status"), workspace, timeout=120).stdout
    counts: dict[str, int] = {}
    for line in shown.splitlines():
        words = line.split()
        if words and words[-1] in ("Queued", "Running", "Success", "Failed"):
            counts[words[-1]] = counts.get(words[-1], 0) + 1
    workers = re.search(r"Worker status: (\d+) active, (\d+) idle", shown)
    return counts, (int(workers[1]) + int(workers[2])) if workers else 0


def start_queue_workers(workspace: Path, jobs: int) -> None:
    """``dvc queue start -j jobs``; its output goes to a file, as the workers it spawns keep its pipes open."""
    log = workspace / ".dvc" / "tmp" / "queue-start.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("a") as output:
        started = subprocess.run(
            dvc("queue", "start", "-j", str(jobs)),
            cwd=workspace,
            env=tool_env(),
            stdout=output,
            stderr=output,
            timeout=120,
        )
    assert started.returncode == 0, log.read_text()[-3000:]


def run_queued_experiments(workspace: Path, jobs: int, timeout: float = 1800, stall_seconds: float = 90) -> int:
    """Start ``jobs`` queue workers (``dvc queue start -j``, as ``dvc exp run --run-all --jobs`` does) and wait until
    no experiment is queued or running; returns how often stalled workers were restarted.

    DVC's queue can leave an experiment queued after every worker has exited (treeverse/dvc#10398, #10562): a user
    then runs ``dvc queue start`` again, and so does this, when experiments stay queued with no worker alive for
    ``stall_seconds``. On timeout, raises with the queue's status and the workers' logs.
    """
    start_queue_workers(workspace, jobs)
    deadline, restarts, stalled_since = time.monotonic() + timeout, 0, None
    while time.monotonic() < deadline:
        counts, workers = queue_status(workspace)
        if not counts.get("Queued") and not counts.get("Running"):
            return restarts
        if counts.get("Queued") and workers == 0:
            stalled_since = stalled_since or time.monotonic()
            if time.monotonic() - stalled_since > stall_seconds:
                start_queue_workers(workspace, jobs)
                restarts, stalled_since = restarts + 1, None
        else:
            stalled_since = None
        time.sleep(10)
    logs = "\n".join(
        f"--- {path.name}\n{path.read_text(errors='replace')[-2000:]}"
        for path in sorted((workspace / ".dvc" / "tmp" / "exps" / "celery").glob("*.out"))
    )
    raise AssertionError(
        f"queued experiments unfinished after {timeout:.0f} s\n{run(dvc('queue', 'status'), workspace).stdout}\n{logs}"
    )
