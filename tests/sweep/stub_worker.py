"""A sweep worker process with a stub pipeline, for tests of several workers sharing one study.

    python -m tests.sweep.stub_worker --storage URL --study NAME --trials N --reports DIR --log FILE
        [--schedules '[[4],[1,4]]'] [--sizes '[4,8]'] [--seconds S] [--tracking-uri URI]

Each trial appends ``start <point> <pid>`` to the log when its experiment starts and ``end <point> <pid>`` when it
ends (after ``--seconds`` of sleep), so a test can tell which worker ran what, whatever the study records.
"""

import argparse
import json
import logging
import os
import time
from pathlib import Path

from carp.config import SweepConfig
from carp.sweep.outcome import ExperimentResult
from carp.sweep.space import TrialSettings, point_key
from carp.sweep.study import run_sweep
from carp.sweep.tracking import SweepTracker


class SleepingRunner:
    """Tokenizer error and success from the settings; every experiment sleeps and is logged."""

    def __init__(self, log: Path, seconds: float) -> None:
        self.log = log
        self.seconds = seconds

    def train_tokenizer(self, name: str, settings: TrialSettings) -> float:
        return 10.0

    def run_experiment(self, name: str, settings: TrialSettings, on_validated) -> ExperimentResult:
        self._write("start", settings)
        time.sleep(self.seconds)
        self._write("end", settings)
        return ExperimentResult(
            validation_success_rate=settings.codebook_size / 100,
            latency_ms=float(settings.num_scales),
            tokenizer_rmse_percent=10.0,
        )

    def _write(self, event: str, settings: TrialSettings) -> None:
        # One short append per line: lines from several processes do not interleave.
        with self.log.open("a") as handle:
            handle.write(f"{event} {point_key(settings)} {os.getpid()}\n")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--storage", required=True)
    parser.add_argument("--study", required=True)
    parser.add_argument("--trials", type=int, required=True)
    parser.add_argument("--reports", type=Path, required=True)
    parser.add_argument("--log", type=Path, required=True)
    parser.add_argument("--schedules", default="[[4], [1, 4], [1, 2, 4]]")
    parser.add_argument("--sizes", default="[4, 8]")
    parser.add_argument("--seconds", type=float, default=0.0)
    parser.add_argument("--tracking-uri")
    arguments = parser.parse_args()
    logging.basicConfig(level=logging.INFO)
    config = SweepConfig(
        study_name=arguments.study,
        storage=arguments.storage,
        num_trials=arguments.trials,
        scale_schedules=tuple(tuple(schedule) for schedule in json.loads(arguments.schedules)),
        codebook_sizes=tuple(json.loads(arguments.sizes)),
        heartbeat_seconds=1,
    )
    tracker = None
    if arguments.tracking_uri:
        tracker = SweepTracker(arguments.tracking_uri, "carp-sweep", {"carp.worker": str(os.getpid())})
    result = run_sweep(config, SleepingRunner(arguments.log, arguments.seconds), arguments.reports, tracker)
    print(f"finished {result.finished_trials}")


if __name__ == "__main__":
    main()
