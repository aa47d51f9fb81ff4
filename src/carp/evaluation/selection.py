"""Checkpoint selection that never looks at the test seeds.

A training run leaves candidate policies: the final one and the snapshots it kept (`carp.training.loop`). Diffusion
Policy and robomimic report the best of many checkpoint evaluations scored on the same test initial states, so the
test set picks the checkpoint and the figure is biased upwards (a true 80% policy scores about 0.92 as the maximum of
60 evaluations of 50 episodes). Here a rule picks one candidate from what training and the *validation* seeds say;
only then does the chosen one run on the test seeds, once. `evaluate_with_selection` is the one place that order is
kept, and the validation figures it returns let the report show the optimistic numbers next to the confirmed one.
"""

import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

from carp.config.checks import SELECTION_RULES
from carp.config.evaluation import EvalConfig

Outcome = TypeVar("Outcome")

FINAL_POLICY_NAME = "policy.pt"
AVERAGED_POLICY_NAME = "averaged.pt"
_SNAPSHOT_NAME = re.compile(r"^epoch(\d+)\.pt$")


@dataclass(frozen=True)
class Candidate:
    """A policy a training run left behind.

    Attributes:
        epoch: the epoch (1-based) after which it was saved.
        path: its checkpoint file.
        training_loss: the mean training loss of that epoch.
    """

    epoch: int
    path: Path
    training_loss: float


@dataclass(frozen=True)
class CandidateScore:
    """A candidate's result on the validation seeds: its successes out of the episodes it ran."""

    candidate: Candidate
    successes: int
    episodes: int

    @property
    def success_rate(self) -> float:
        """Successes over episodes."""
        return self.successes / self.episodes


@dataclass(frozen=True)
class Selection:
    """The chosen candidate, by which rule, and every candidate's validation score (empty without validation).

    With ``average_last`` the policy evaluated on the test seeds is the mean of `averaged`'s weights; `chosen` is the
    latest of them.
    """

    chosen: Candidate
    rule: str
    validation: tuple[CandidateScore, ...] = ()
    averaged: tuple[Candidate, ...] = ()

    def validation_summary(self, top_k: int) -> dict[str, float]:
        """What the validation episodes say, next to which the report puts the confirmed test success.

        Keys: ``selected_epoch``, ``averaged_checkpoints`` (with ``average_last``: how many were averaged, up to
        the selected epoch), and with validation episodes ``validation_max_success_rate`` (the best candidate, what
        test-set selection would report), ``validation_top_k_mean_success_rate`` (the mean of the `top_k` best,
        Diffusion Policy's other figure), ``validation_top_k`` and, when a single candidate was chosen,
        ``selected_validation_success_rate``.
        """
        summary: dict[str, float] = {"selected_epoch": self.chosen.epoch}
        if self.averaged:
            summary["averaged_checkpoints"] = len(self.averaged)
        if not self.validation:
            return summary
        rates = sorted((score.success_rate for score in self.validation), reverse=True)
        kept = rates[: min(top_k, len(rates))]
        summary |= {
            "validation_max_success_rate": rates[0],
            "validation_top_k_mean_success_rate": sum(kept) / len(kept),
            "validation_top_k": len(kept),
        }
        if not self.averaged:
            chosen = next(score for score in self.validation if score.candidate == self.chosen)
            summary["selected_validation_success_rate"] = chosen.success_rate
        return summary


def find_candidates(policy_dir: Path, epoch_losses: Sequence[float]) -> list[Candidate]:
    """The final policy and the kept snapshots of one training run, by epoch.

    Args:
        policy_dir: the run's output directory (`policy.pt` and `snapshots/epoch<NNNN>.pt`).
        epoch_losses: the mean training loss of every epoch, in order (the run's history); the final policy is the
            last epoch's.

    Raises:
        FileNotFoundError: there is no final policy.
        ValueError: the history is empty or a snapshot's epoch lies beyond it.
    """
    policy_dir = Path(policy_dir)
    final = policy_dir / FINAL_POLICY_NAME
    if not final.exists():
        raise FileNotFoundError(f"{final}: no trained policy (run the train_policy stage)")
    if not epoch_losses:
        raise ValueError(f"{policy_dir}: the training history has no epoch")
    found = {len(epoch_losses): Candidate(len(epoch_losses), final, float(epoch_losses[-1]))}
    for path in sorted((policy_dir / "snapshots").glob("epoch*.pt")):
        match = _SNAPSHOT_NAME.match(path.name)
        if match is None:
            continue
        epoch = int(match.group(1))
        if not 1 <= epoch <= len(epoch_losses):
            raise ValueError(f"{path}: epoch {epoch} lies outside the training history's {len(epoch_losses)} epochs")
        found.setdefault(epoch, Candidate(epoch, path, float(epoch_losses[epoch - 1])))
    return [found[epoch] for epoch in sorted(found)]


def select_candidate(
    candidates: Sequence[Candidate], rule: str, validation: Sequence[CandidateScore] = (), average_last: int = 1
) -> Selection:
    """Apply `rule` (one of `carp.config.SELECTION_RULES`); ties go to the later epoch.

    Args:
        candidates: at least one.
        rule: ``final`` (the last epoch), ``lowest_loss`` (the lowest training loss), ``best_validation`` (the
            most validation successes, which needs a score per candidate) or ``average_last`` (the latest
            `average_last` candidates, to be averaged).
        validation: the candidates' validation scores, if any ran.
        average_last: with ``average_last``, how many candidates; at most as many as there are.

    Raises:
        ValueError: no candidate, an unknown rule, best_validation without a score for every candidate, or fewer
            candidates than `average_last`.
    """
    if not candidates:
        raise ValueError("there is no candidate policy to select from")
    if rule not in SELECTION_RULES:
        raise ValueError(f"selection rule {rule!r} must be one of {SELECTION_RULES}")
    if rule == "average_last":
        if not 1 <= average_last <= len(candidates):
            epochs = [candidate.epoch for candidate in candidates]
            raise ValueError(
                f"average_last={average_last}: the training kept {len(candidates)} candidates (epochs {epochs}); keep "
                "more snapshots (training.snapshot_every, snapshot_last) or average fewer"
            )
        latest = tuple(sorted(candidates, key=lambda candidate: candidate.epoch)[-average_last:])
        return Selection(latest[-1], rule, tuple(validation), latest)
    if rule == "final":
        chosen = max(candidates, key=lambda candidate: candidate.epoch)
    elif rule == "lowest_loss":
        chosen = min(candidates, key=lambda candidate: (candidate.training_loss, -candidate.epoch))
    else:
        scores = {score.candidate: score for score in validation}
        missing = [candidate.epoch for candidate in candidates if candidate not in scores]
        if missing:
            raise ValueError(f"best_validation needs validation episodes; epochs {missing} have none")
        chosen = max(candidates, key=lambda candidate: (scores[candidate].success_rate, candidate.epoch))
    return Selection(chosen, rule, tuple(validation))


@dataclass(frozen=True)
class SelectedEvaluation(Generic[Outcome]):
    """What `evaluate_with_selection` ran.

    Attributes:
        selection: the chosen candidate and the validation scores.
        validation: epoch -> that candidate's validation outcome (as `run_episodes` returned it).
        test: the chosen candidate's outcome on the test seeds; None when no test episode ran
            (`evaluate_as_configured` with ``eval.run_test: false``).
        tested: the checkpoint that ran on the test seeds (the chosen candidate's, or the averaged policy's); without
            test episodes, the chosen candidate's.
    """

    selection: Selection
    validation: dict[int, Outcome]
    test: Outcome | None
    tested: Path


@dataclass(frozen=True)
class ValidatedSelection(Generic[Outcome]):
    """What `validate_and_select` ran: the choice and every candidate's validation outcome, no test episode.

    Attributes:
        selection: the chosen candidate and the validation scores.
        validation: epoch -> that candidate's validation outcome (as `run_episodes` returned it).
    """

    selection: Selection
    validation: dict[int, Outcome]


def validate_and_select(
    candidates: Sequence[Candidate],
    rule: str,
    run_episodes: Callable[[Path, list[int]], Outcome],
    successes_of: Callable[[Outcome], list[bool]],
    validation_seeds: Sequence[int],
    average_last: int = 1,
    on_validated: Callable[[Candidate, Outcome], None] | None = None,
) -> ValidatedSelection[Outcome]:
    """Score every candidate on the validation seeds, by epoch, and apply `rule`; runs no test episode.

    Args:
        candidates: the run's candidates (`find_candidates`).
        rule: see `select_candidate`.
        run_episodes: runs a checkpoint on seeds, one episode each, and returns an outcome.
        successes_of: the per-episode successes of an outcome, in seed order.
        validation_seeds: episodes per candidate; may be empty (then no validation runs).
        average_last: see `select_candidate`.
        on_validated: called after each candidate's validation, in epoch order, e.g. to report it to a sweep; an
            exception it raises stops the validation there (the later candidates never run).

    Raises:
        ValueError: the rule cannot be applied.
    """
    validation: dict[int, Outcome] = {}
    scores = []
    if validation_seeds:
        for candidate in sorted(candidates, key=lambda candidate: candidate.epoch):
            outcome = run_episodes(candidate.path, list(validation_seeds))
            successes = successes_of(outcome)
            validation[candidate.epoch] = outcome
            scores.append(CandidateScore(candidate, int(sum(bool(s) for s in successes)), len(successes)))
            if on_validated is not None:
                on_validated(candidate, outcome)
    return ValidatedSelection(select_candidate(candidates, rule, scores, average_last), validation)


def evaluate_with_selection(
    candidates: Sequence[Candidate],
    rule: str,
    run_episodes: Callable[[Path, list[int]], Outcome],
    successes_of: Callable[[Outcome], list[bool]],
    validation_seeds: Sequence[int],
    test_seeds: Sequence[int],
    average_last: int = 1,
    average: Callable[[Sequence[Candidate]], Path] | None = None,
    on_validated: Callable[[Candidate, Outcome], None] | None = None,
) -> SelectedEvaluation[Outcome]:
    """Score every candidate on the validation seeds, fix the choice, then run the chosen one on the test seeds.

    The order is the guarantee: no test seed runs before the choice is made, and no validation episode uses a test
    seed.

    Args:
        candidates: the run's candidates (`find_candidates`).
        rule: see `select_candidate`.
        run_episodes: runs a checkpoint on seeds, one episode each, and returns an outcome.
        successes_of: the per-episode successes of an outcome, in seed order.
        validation_seeds: episodes per candidate; may be empty (then no validation runs).
        test_seeds: episodes of the chosen candidate; at least one.
        average_last: see `select_candidate`.
        average: with ``average_last``, writes the policy whose weights are the mean of the given candidates' and
            returns its checkpoint, which then runs on the test seeds.
        on_validated: see `validate_and_select`.

    Raises:
        ValueError: the two seed lists share a seed, there is no test seed, or the rule cannot be applied.
    """
    shared = sorted(set(validation_seeds) & set(test_seeds))
    if shared:
        raise ValueError(f"validation and test seeds must be disjoint; both hold {shared[:5]}")
    if not test_seeds:
        raise ValueError("there is no test seed")
    validated = validate_and_select(
        candidates, rule, run_episodes, successes_of, validation_seeds, average_last, on_validated
    )
    selection = validated.selection
    tested = selection.chosen.path
    if selection.averaged:
        if average is None:
            raise ValueError("average_last needs a way to average the candidates' weights")
        tested = average(selection.averaged)
    test = run_episodes(tested, list(test_seeds))
    return SelectedEvaluation(selection, validated.validation, test, Path(tested))


def evaluate_as_configured(
    config: EvalConfig,
    candidates: Sequence[Candidate],
    run_episodes: Callable[[Path, list[int]], Outcome],
    successes_of: Callable[[Outcome], list[bool]],
    average: Callable[[Sequence[Candidate]], Path] | None = None,
    on_validated: Callable[[Candidate, Outcome], None] | None = None,
) -> SelectedEvaluation[Outcome]:
    """The evaluate stage's episodes as the ``eval`` section asks for them.

    That is `evaluate_with_selection`, or with ``run_test: false`` `validate_and_select` alone: then the result's
    ``test`` is None and no test seed runs.

    Args:
        config: the ``eval`` section (selection rule, seeds, ``average_last``, ``run_test``).
        candidates: see `evaluate_with_selection`.
        run_episodes: see `evaluate_with_selection`.
        successes_of: see `evaluate_with_selection`.
        average: see `evaluate_with_selection`.
        on_validated: see `validate_and_select`.
    """
    if config.run_test:
        return evaluate_with_selection(
            candidates,
            config.selection,
            run_episodes,
            successes_of,
            config.validation_seeds(),
            config.test_seeds(),
            config.average_last,
            average,
            on_validated,
        )
    validated = validate_and_select(
        candidates,
        config.selection,
        run_episodes,
        successes_of,
        config.validation_seeds(),
        config.average_last,
        on_validated,
    )
    chosen = validated.selection.chosen
    return SelectedEvaluation(validated.selection, validated.validation, None, Path(chosen.path))


# Figures of the selected candidate's validation episodes that a validation-only summary carries, renamed so that
# nothing reads them as test figures.
VALIDATION_FIGURES = ("score", "success_rate", "success_rate_ci_low", "success_rate_ci_high", "successes", "episodes")


def validation_only_summary(outcome: tuple[dict[str, Any], list]) -> dict[str, Any]:
    """The summary of an evaluation without test episodes (``eval.run_test: false``): the selected candidate's.

    Args:
        outcome: the selected candidate's validation outcome, (summary, episodes) of
            `carp.evaluation.runner.evaluate_policy`.

    Returns:
        Its latency, policy facts and backend as the validation episodes gave them; its success figures with the
        ``validation_`` prefix, and ``test_episodes`` 0.
    """
    validation, _ = outcome
    summary = {key: value for key, value in validation.items() if key not in VALIDATION_FIGURES}
    summary.update({f"validation_{key}": validation[key] for key in VALIDATION_FIGURES if key in validation})
    summary["test_episodes"] = 0
    return summary


def save_averaged_policy(candidates: Sequence[Candidate], path: Path) -> Path:
    """Write at `path` the policy whose weights are the mean of `candidates`' (`average_policies`); returns `path`.

    Its metadata lists the averaged epochs. The bytes depend on the candidates alone (`atomic_torch_save` does not
    name the archive after the file), so rebuilding the average after the evaluation gives the file it ran.
    """
    from carp.policies.registry import average_policies

    averaged = average_policies([candidate.path for candidate in candidates])
    averaged.metadata["averaged_epochs"] = [candidate.epoch for candidate in candidates]
    averaged.save(path)
    return Path(path)


def confirmed_checkpoint(candidates: Sequence[Candidate], summary: Mapping[str, Any], scratch: Path) -> Path:
    """The checkpoint that an evaluation ran on the test seeds, found from its summary among the run's candidates.

    The summary (the evaluate stage's ``seed<k>.json``, `Selection.validation_summary`) names the chosen candidate's
    ``selected_epoch`` and, with ``average_last``, how many of the latest candidates up to it were averaged
    (``averaged_checkpoints``); that average is rebuilt (`save_averaged_policy`) in `scratch`.

    Args:
        candidates: the run's candidates (`find_candidates`), as the evaluation saw them.
        summary: the evaluation summary.
        scratch: an existing directory for the averaged policy; the caller removes it.

    Raises:
        ValueError: the summary ran no test episode or names no selected epoch, or one (or averaged candidates) that
            the run does not hold.
    """
    if summary.get("test_episodes") == 0:
        raise ValueError("the evaluation ran no test episode (eval.run_test: false): it confirmed no checkpoint")
    if "selected_epoch" not in summary:
        raise ValueError("the evaluation summary names no selected_epoch (evaluate it again)")
    epoch = int(summary["selected_epoch"])
    up_to_selected = sorted(
        (candidate for candidate in candidates if candidate.epoch <= epoch), key=lambda candidate: candidate.epoch
    )
    if not up_to_selected or up_to_selected[-1].epoch != epoch:
        kept = [candidate.epoch for candidate in candidates]
        raise ValueError(f"the evaluation selected epoch {epoch}, which is not among the run's candidates {kept}")
    averaged = int(summary.get("averaged_checkpoints", 0))
    if not averaged:
        return up_to_selected[-1].path
    if averaged > len(up_to_selected):
        raise ValueError(
            f"the evaluation averaged the last {averaged} candidates up to epoch {epoch}, but the run holds "
            f"{len(up_to_selected)} (epochs {[candidate.epoch for candidate in up_to_selected]})"
        )
    return save_averaged_policy(up_to_selected[-averaged:], Path(scratch) / AVERAGED_POLICY_NAME)
