"""Validation progress that another process follows while the evaluate stage runs, and may stop.

The sweep runs each trial as a DVC experiment in a child process and wants each candidate's validation score as soon
as it exists, so that Optuna's pruner can stop a poor trial before its later candidates (and the stages after them)
run. The evaluate stage appends one JSON line per validated candidate to a progress file and, after each, looks for a
stop file beside it; the sweep reads the new lines, reports them to Optuna and writes the stop file when the trial is
pruned. A file pair rather than a pipe because DVC sits between the two processes and passes on only the environment,
which names the progress file (:data:`PROGRESS_VARIABLE`).
"""

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

PROGRESS_VARIABLE = "CARP_VALIDATION_PROGRESS"
"""Environment variable naming the progress file; the evaluate stage writes none when it is unset."""


class ValidationStopped(RuntimeError):
    """The process following the progress asked the evaluation to stop (a pruned sweep trial)."""


@dataclass(frozen=True)
class ValidatedCandidate:
    """One candidate's validation, as the progress file carries it.

    Attributes:
        evaluation: which evaluation it belongs to, ``<task>/<label>/seed<k>``.
        epoch: the candidate's epoch (1-based).
        score: the task's score on the validation episodes, in [0, 1].
        success_rate: successes over validation episodes.
    """

    evaluation: str
    epoch: int
    score: float
    success_rate: float


class ProgressFile:
    """A progress file (JSON lines) and the stop file beside it (``<name>.stop``)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.stop_path = self.path.with_name(f"{self.path.name}.stop")

    def clear(self) -> None:
        """Remove both files, before a new run."""
        self.path.unlink(missing_ok=True)
        self.stop_path.unlink(missing_ok=True)

    def append(self, candidate: ValidatedCandidate) -> None:
        """Add one line; written in one call and flushed, so a reader never sees half of it as a whole line."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self.path.open("a") as handle:
            handle.write(json.dumps(asdict(candidate)) + "\n")
            handle.flush()
            os.fsync(handle.fileno())

    def read(self, offset: int) -> tuple[list[ValidatedCandidate], int]:
        """The complete lines from byte `offset` on, and the offset after the last of them."""
        if not self.path.exists():
            return [], offset
        with self.path.open("rb") as handle:
            handle.seek(offset)
            data = handle.read()
        complete = data[: data.rfind(b"\n") + 1]
        lines = complete.decode().splitlines()
        return [ValidatedCandidate(**json.loads(line)) for line in lines if line.strip()], offset + len(complete)

    def request_stop(self) -> None:
        """Ask the evaluation to stop after the candidate it is validating."""
        self.stop_path.parent.mkdir(parents=True, exist_ok=True)
        self.stop_path.touch()

    def stop_requested(self) -> bool:
        """Whether a stop was asked for."""
        return self.stop_path.exists()
