"""The sweep's closing confirmation: the selected settings against the default ones, on the test seeds.

The sweep picks the best of many trials on the validation seeds, so the winner's validation score is optimistic (the
best of 16 equal trials measured on 50 episodes reads about 9 points high). The confirmation measures the choice
afresh: the winner's settings and the default settings (``scales`` and ``codebook_size`` of the committed params
file) are each trained once per ``sweep.confirm_seeds`` training seed, as one DVC experiment each, and evaluated on
the test seeds that no trial ran. The confirmation's training seeds are none of the trials' (the sweep checks it): a
trial's network was chosen for its validation score, and reusing it would carry that luck into the selected arm. The
paired comparison of the two (`carp.reporting.comparison.compare_families`, the report's own verdicts, with
``comparison.margin`` and ``comparison.alpha``) is the sweep's result. When the winner's settings are the default
ones, one experiment runs and there is nothing to compare.

Each arm's evaluations are copied under ``<reports>/confirmation/<arm>/`` as soon as its experiment ends (the next
experiment overwrites the workspace's outputs), so a resumed sweep does not train an arm again.
"""

import json
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from carp.reporting.comparison import compare_families
from carp.reporting.runs import RunResults, read_run_results
from carp.sweep.outcome import TrialRecord
from carp.sweep.space import TrialSettings

logger = logging.getLogger(__name__)

LabelledRuns = dict[str, dict[int, RunResults]]
"""Evaluated run label (the task, or ``<task>-<policy>`` with several policies) -> training seed -> its results."""

CONFIRMATION_DIRECTORY = "confirmation"
ARM_FILE = "arm.json"
SELECTED, DEFAULT = "selected", "default"


@dataclass(frozen=True)
class ConfirmationPlan:
    """What the confirmation compares and how.

    Attributes:
        default: the committed params file's ``scales`` and ``codebook_size``.
        seeds: training seeds of each arm (``sweep.confirm_seeds``).
        margin: equivalence margin of the verdict, in success rate (``comparison.margin``).
        alpha: significance level of the verdict (``comparison.alpha``).
        min_seeds: training seeds per arm a verdict needs (``comparison.min_seeds``); fewer seeds confirm nothing.
        worker: names this worker's workspace (host and path); among workers sharing a study the first to get
            there runs the confirmation, and a restart in the same workspace resumes it.
    """

    default: TrialSettings
    seeds: tuple[int, ...]
    margin: float
    alpha: float
    worker: str
    min_seeds: int = 3


@dataclass(frozen=True)
class ConfirmationResult:
    """The two arms on the test seeds and their verdicts.

    Attributes:
        best: the trial the sweep selected on the validation seeds.
        plan: what was compared.
        experiments: the DVC experiment of each arm (one when the settings are the default ones).
        selected_runs: the selected settings' evaluations.
        comparisons: label -> the paired comparison, ``selected`` first; empty when the settings are the default.
    """

    best: TrialRecord
    plan: ConfirmationPlan
    experiments: tuple[str, ...]
    selected_runs: LabelledRuns
    comparisons: Mapping[str, object]

    @property
    def same_settings(self) -> bool:
        """Whether the selected settings are the default ones."""
        return self.best.settings == self.plan.default

    def test_success_rates(self) -> dict[str, float]:
        """Label -> the selected settings' test success over every training seed's episodes."""
        return {label: pooled_success(runs) for label, runs in self.selected_runs.items()}

    def lines(self) -> list[str]:
        """The confirmation as the sweep reports it: the winner's validation and test figures, then each verdict."""
        best = self.best
        assert best.objective is not None and best.validation_success_rate is not None
        seeds = list(self.plan.seeds)
        lines = [
            f"trial {best.number} ({best.dvc_experiment}), selected on the validation seeds: validation score "
            f"{best.objective:.3f}, validation success {100 * best.validation_success_rate:.1f}%",
        ]
        if self.same_settings:
            lines.append(
                f"confirmation ({self.experiments[0]}, training seeds {seeds}): the selected settings are the default "
                "ones, trained once; nothing to compare"
            )
            lines += [
                f"{label}: validation success {100 * best.validation_success_rate:.1f}% | test success "
                f"{100 * rate:.1f}%"
                for label, rate in self.test_success_rates().items()
            ]
            return lines
        lines.append(
            f"confirmation ({', '.join(self.experiments)}, training seeds {seeds}) against the default settings "
            f"{self.plan.default.command_line()} on the test seeds:"
        )
        for label, comparison in self.comparisons.items():
            lines.append(
                f"{label}: validation success {100 * best.validation_success_rate:.1f}% | test success "
                f"{100 * comparison.first_rate:.1f}% selected, {100 * comparison.second_rate:.1f}% default: "
                f"{comparison.verdict}. {comparison.explanation}"
            )
        return lines

    def metrics(self) -> dict[str, float]:
        """Figures for the MLflow parent run: the selected and default test success, mean over labels."""
        rates = self.test_success_rates()
        figures = {"confirmed_test_success_rate": sum(rates.values()) / len(rates)}
        if self.comparisons:
            figures["default_test_success_rate"] = sum(c.second_rate for c in self.comparisons.values()) / len(
                self.comparisons
            )
        return figures

    def verdicts(self) -> dict[str, str]:
        """Label -> verdict (``"the default settings"`` when there was nothing to compare)."""
        if self.same_settings:
            return {label: "the default settings" for label in self.selected_runs}
        return {label: comparison.verdict for label, comparison in self.comparisons.items()}


def pooled_success(runs: Mapping[int, RunResults]) -> float:
    """Successes over episodes, every training seed's test episodes together."""
    successes = sum(int(run.episodes["success"].astype(bool).sum()) for run in runs.values())
    episodes = sum(len(run.episodes) for run in runs.values())
    return successes / episodes if episodes else float("nan")


def arm_key(settings: TrialSettings, seeds: Sequence[int]) -> str:
    """An arm's name in experiment names and folders: ``s1-2-4-v256-seeds0-1-2`` (git ref and path safe)."""
    return f"s{'-'.join(map(str, settings.scales))}-v{settings.codebook_size}-seeds{'-'.join(map(str, seeds))}"


def confirmation_experiment_name(study_name: str, settings: TrialSettings, seeds: Sequence[int]) -> str:
    """DVC experiment name of one arm, e.g. ``sweep-carp-sweep-confirm-s1-2-4-v256-seeds0-1-2``."""
    return f"sweep-{study_name}-confirm-{arm_key(settings, seeds)}"


def save_arm(directory: Path, name: str, runs: LabelledRuns) -> None:
    """Copy an arm's evaluations to ``directory`` (``<label>/seed<k>.json`` and its episodes), then its marker."""
    for label, by_seed in runs.items():
        for seed, run in by_seed.items():
            summary = directory / label / f"seed{seed}.json"
            summary.parent.mkdir(parents=True, exist_ok=True)
            summary.write_text(json.dumps(dict(run.metrics), indent=2, default=str))
            run.episodes.to_csv(summary.with_name(f"seed{seed}_episodes.csv"), index=False)
    # Written last: an arm without it was interrupted while being copied and runs again.
    (directory / ARM_FILE).write_text(json.dumps({"experiment": name, "labels": sorted(runs)}))


def load_arm(directory: Path, seeds: Sequence[int]) -> tuple[str, LabelledRuns] | None:
    """An arm saved by `save_arm`, or None when it is missing or incomplete."""
    marker = directory / ARM_FILE
    if not marker.is_file():
        return None
    saved = json.loads(marker.read_text())
    runs = {
        label: {seed: read_run_results(directory / label / f"seed{seed}.json") for seed in seeds}
        for label in saved["labels"]
    }
    return saved["experiment"], runs


def confirm(
    best: TrialRecord,
    plan: ConfirmationPlan,
    study_name: str,
    run_arm: Callable[[str, TrialSettings, Sequence[int]], LabelledRuns],
    report_directory: Path,
) -> ConfirmationResult:
    """Train and test the selected and the default settings (each arm once, resuming saved arms); their verdicts.

    Args:
        best: the selected trial (completed, with settings).
        plan: the default settings, seeds and verdict settings.
        study_name: names the arms' DVC experiments.
        run_arm: trains the given settings with each seed as the named DVC experiment and evaluates them on the
            test seeds (`carp.sweep.study.ExperimentRunner.run_confirmation`).
        report_directory: the sweep's report folder; arms are kept under its ``confirmation/``.
    """
    assert best.settings is not None
    arms = [best.settings] if best.settings == plan.default else [best.settings, plan.default]
    experiments, evaluated = [], []
    for settings in arms:
        directory = Path(report_directory) / CONFIRMATION_DIRECTORY / arm_key(settings, plan.seeds)
        saved = load_arm(directory, plan.seeds)
        if saved is None:
            name = confirmation_experiment_name(study_name, settings, plan.seeds)
            logger.info("confirmation: %s as %s, training seeds %s", settings.command_line(), name, list(plan.seeds))
            runs = run_arm(name, settings, plan.seeds)
            save_arm(directory, name, runs)
            saved = (name, runs)
        else:
            logger.info("confirmation: %s already ran as %s", settings.command_line(), saved[0])
        experiments.append(saved[0])
        evaluated.append(saved[1])
    comparisons = {}
    if len(arms) == 2:
        evaluations = {label: {SELECTED: evaluated[0][label], DEFAULT: evaluated[1][label]} for label in evaluated[0]}
        decided = compare_families(evaluations, margin=plan.margin, alpha=plan.alpha, min_seeds=plan.min_seeds)
        comparisons = {label: decided[label][0] for label in evaluations}
    return ConfirmationResult(best, plan, tuple(experiments), evaluated[0], comparisons)
