"""Optuna's pruner fed with the validation scores of a trial's training snapshots.

A trial's evaluate stages validate every candidate of every run (the snapshots and the final policy, by epoch) and
append each result to a progress file as it finishes (`carp.evaluation.progress`); the sweep reports each one to
Optuna at once (``trial.report``) and asks the pruner. A pruned trial's evaluation stops after the candidate it is
validating, so the later candidates' validation episodes and the evaluations DVC has not yet run are saved. The
trainings are not: DVC runs every training of an experiment (``train_policy`` of each task and seed) before its
first evaluation, and the snapshots are validated only then, inside the evaluate stage.

The reported curve (:class:`ValidationCurve`): step ``k`` is the ``k``-th validated candidate of the trial, in the
order DVC runs the evaluations and each evaluation its candidates (the same for every trial of a study, whose
trials differ only in the tokenizer's settings); its value is the mean, over the evaluations begun so far, of each
one's best validation score so far, i.e. what the trial would score if it stopped there. Its last value is the
trial's objective whenever the selection picks the best-scoring candidate.

Pruners (Optuna's asynchronous versions): successive halving keeps at each rung (steps 1, 3, 9, ...) the trials in
the top third of those that reached it so far; while fewer than three have, only a trial at least as good as the
best of them goes on, so early in a study it prunes hard. Hyperband runs several such brackets with different first
rungs, so that some trials are judged only late, and prunes nothing until one trial has finished (it learns the
number of steps from it). A validation score of a few dozen episodes is noisy and an early snapshot says little
about the final policy: pruning trades some chance of losing a good trial for compute, which ``none`` does not.
"""

from dataclasses import dataclass, field

import optuna

from carp.config.experiments import SweepConfig
from carp.evaluation.progress import ValidatedCandidate

REDUCTION_FACTOR = 3


def make_pruner(config: SweepConfig) -> optuna.pruners.BasePruner:
    """The pruner that ``sweep.pruner`` names."""
    if config.pruner == "successive_halving":
        return optuna.pruners.SuccessiveHalvingPruner(min_resource=1, reduction_factor=REDUCTION_FACTOR)
    if config.pruner == "hyperband":
        return optuna.pruners.HyperbandPruner(min_resource=1, reduction_factor=REDUCTION_FACTOR)
    return optuna.pruners.NopPruner()


@dataclass
class ValidationCurve:
    """The intermediate values one trial reports, built from its validated candidates (see the module docstring)."""

    steps: int = 0
    best_by_evaluation: dict[str, float] = field(default_factory=dict)

    def add(self, candidate: ValidatedCandidate) -> tuple[int, float]:
        """Take one validated candidate; returns the (step, value) to report."""
        previous = self.best_by_evaluation.get(candidate.evaluation)
        self.best_by_evaluation[candidate.evaluation] = (
            candidate.score if previous is None else max(previous, candidate.score)
        )
        self.steps += 1
        return self.steps, sum(self.best_by_evaluation.values()) / len(self.best_by_evaluation)
