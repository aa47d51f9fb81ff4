"""A fake experiment runner and a tiny sweep config: the study logic without DVC."""

import math
from dataclasses import dataclass, field

import pytest

from carp.config import SweepConfig
from carp.sweep.outcome import ExperimentResult
from carp.sweep.space import TrialSettings


@dataclass
class FakeRunner:
    """Tokenizer error and success derived from the settings; optional failures on chosen calls.

    Attributes:
        errors: codebook size -> tokenizer RMSE (% of range).
        interrupt_on_experiment: 1-based index of the `run_experiment` call that raises KeyboardInterrupt.
        fail_on_experiment: 1-based index of the `run_experiment` call that raises ExperimentFailedError.
    """

    errors: dict[int, float] = field(default_factory=lambda: {4: 10.0, 8: 12.0, 16: 50.0})
    interrupt_on_experiment: int | None = None
    fail_on_experiment: int | None = None
    tokenizer_calls: list[TrialSettings] = field(default_factory=list)
    experiment_calls: list[tuple[str, TrialSettings]] = field(default_factory=list)

    def train_tokenizer(self, name: str, settings: TrialSettings) -> float:
        self.tokenizer_calls.append(settings)
        return self.errors.get(settings.codebook_size, math.nan)

    def run_experiment(self, name: str, settings: TrialSettings) -> ExperimentResult:
        from carp.sweep.study import ExperimentFailedError

        self.experiment_calls.append((name, settings))
        if len(self.experiment_calls) == self.interrupt_on_experiment:
            raise KeyboardInterrupt
        if len(self.experiment_calls) == self.fail_on_experiment:
            raise ExperimentFailedError("`dvc exp run` exited with status 1")
        return ExperimentResult(
            success_rate=expected_success(settings),
            latency_ms=1.0 + settings.num_scales,
            tokenizer_rmse_percent=self.errors[settings.codebook_size],
        )


def expected_success(settings: TrialSettings) -> float:
    """Fake success: more scales are better, capped so that ties appear."""
    return min(settings.num_scales, 2) / 2


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
    )
