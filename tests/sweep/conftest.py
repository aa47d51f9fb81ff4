"""A fake experiment runner and a tiny sweep config: the study logic without DVC."""

import dataclasses
import math
from dataclasses import dataclass, field

import pandas as pd
import pytest

from carp.config import EvalConfig, SweepConfig
from carp.evaluation.progress import ValidatedCandidate
from carp.evaluation.selection import Candidate, evaluate_as_configured
from carp.reporting.runs import RunResults
from carp.sweep.dvc_runner import CONFIRMATION_EVAL_OVERRIDES, TRIAL_EVAL_OVERRIDES
from carp.sweep.outcome import ExperimentResult
from carp.sweep.space import TrialSettings

EVAL = EvalConfig(episodes=40, seed=100_000, validation_episodes=4, validation_seed=200_000)
"""The pipeline's ``eval`` section the fake evaluations start from; each run applies the sweep's overrides to it."""
EPOCHS = (1, 2, 3, 4, 5, 6)
"""Epochs of each fake training's candidates (five snapshots and the final policy)."""


class _Stopped(Exception):
    pass


@dataclass
class FakeRunner:
    """Tokenizer error and success derived from the settings; optional failures on chosen calls.

    Every evaluation goes through `evaluate_as_configured` with the ``eval`` settings the DVC runner sets (trials:
    `TRIAL_EVAL_OVERRIDES`, confirmation: `CONFIRMATION_EVAL_OVERRIDES`), and every episode seed it runs is recorded.

    Attributes:
        errors: codebook size -> tokenizer RMSE (% of range).
        interrupt_on_experiment: 1-based index of the `run_experiment` call that raises KeyboardInterrupt.
        fail_on_experiment: 1-based index of the `run_experiment` call that raises ExperimentFailedError.
        episode_seeds: (experiment name, epoch, the episode seeds one evaluation call ran) in call order.
        validated: experiment name -> how many candidates it validated before it ended or stopped.
    """

    errors: dict[int, float] = field(default_factory=lambda: {4: 10.0, 8: 12.0, 16: 50.0})
    interrupt_on_experiment: int | None = None
    fail_on_experiment: int | None = None
    tokenizer_calls: list[TrialSettings] = field(default_factory=list)
    experiment_calls: list[tuple[str, TrialSettings]] = field(default_factory=list)
    confirmation_calls: list[tuple[str, TrialSettings, tuple[int, ...]]] = field(default_factory=list)
    episode_seeds: list[tuple[str, int, list[int]]] = field(default_factory=list)
    validated: dict[str, int] = field(default_factory=dict)

    def train_tokenizer(self, name: str, settings: TrialSettings) -> float:
        self.tokenizer_calls.append(settings)
        return self.errors.get(settings.codebook_size, math.nan)

    def run_experiment(self, name: str, settings: TrialSettings, on_validated) -> ExperimentResult:
        from carp.sweep.study import ExperimentFailedError, ExperimentStoppedError

        self.experiment_calls.append((name, settings))
        if len(self.experiment_calls) == self.interrupt_on_experiment:
            raise KeyboardInterrupt
        if len(self.experiment_calls) == self.fail_on_experiment:
            raise ExperimentFailedError("`dvc exp run` exited with status 1")
        self.validated[name] = 0

        def report(candidate, outcome):
            self.validated[name] += 1
            rate = sum(outcome) / len(outcome)
            if on_validated(ValidatedCandidate("lift/carp/seed0", candidate.epoch, rate, rate)):
                raise _Stopped

        try:
            evaluated = self._evaluate(name, settings, 0, TRIAL_EVAL_OVERRIDES, report)
        except _Stopped:
            raise ExperimentStoppedError("stopped on request") from None
        assert evaluated.test is None
        chosen = evaluated.validation[evaluated.selection.chosen.epoch]
        return ExperimentResult(
            validation_success_rate=sum(chosen) / len(chosen),
            latency_ms=1.0 + settings.num_scales,
            tokenizer_rmse_percent=self.errors[settings.codebook_size],
        )

    def run_confirmation(self, name: str, settings: TrialSettings, seeds) -> dict[str, dict[int, RunResults]]:
        self.confirmation_calls.append((name, settings, tuple(seeds)))
        runs = {}
        for seed in seeds:
            evaluated = self._evaluate(name, settings, seed, CONFIRMATION_EVAL_OVERRIDES, None)
            config = dataclasses.replace(EVAL, **CONFIRMATION_EVAL_OVERRIDES)
            episodes = pd.DataFrame(
                {"seed": config.test_seeds(), "success": evaluated.test, "steps": [100] * len(evaluated.test)}
            )
            rate = float(episodes["success"].mean())
            runs[seed] = RunResults({"success_rate": rate, "score": rate}, episodes)
        return {"lift": runs}

    def _evaluate(self, name, settings, training_seed, overrides, on_validated):
        config = dataclasses.replace(EVAL, **overrides)
        candidates = [Candidate(epoch, f"epoch{epoch}", 1.0 / epoch) for epoch in EPOCHS]

        def run_episodes(path, seeds):
            epoch = int(path.removeprefix("epoch"))
            self.episode_seeds.append((name, epoch, list(seeds)))
            rate = fake_success(settings, epoch, training_seed)
            return [(index + 0.5) / len(seeds) < rate for index in range(len(seeds))]

        return evaluate_as_configured(config, candidates, run_episodes, lambda outcome: outcome, None, on_validated)


def expected_success(settings: TrialSettings) -> float:
    """Fake success of the final policy: more scales are better, capped so that ties appear."""
    return min(settings.num_scales, 2) / 2


def fake_success(settings: TrialSettings, epoch: int, training_seed: int = 0) -> float:
    """Fake success of a candidate: grows with the epoch up to `expected_success`; other training seeds a bit less."""
    return expected_success(settings) * epoch / EPOCHS[-1] - 0.1 * training_seed


@pytest.fixture
def sweep_config(tmp_path) -> SweepConfig:
    return SweepConfig(
        study_name="unit",
        storage=f"sqlite:///{tmp_path / 'optuna.db'}",
        num_trials=3,
        scale_schedules=((4,), (1, 4), (1, 2, 4)),
        codebook_sizes=(4, 8),
        prune_factor=2.0,
        heartbeat_seconds=1,
        pruner="none",
    )
