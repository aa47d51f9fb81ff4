"""Checkpoint selection: candidates on disk, the rules, and that no test seed runs before the choice is fixed."""

from pathlib import Path

import pytest
import torch

from carp.evaluation.selection import (
    Candidate,
    CandidateScore,
    confirmed_checkpoint,
    evaluate_with_selection,
    find_candidates,
    save_averaged_policy,
    select_candidate,
    validate_and_select,
    validation_only_summary,
)
from carp.policies.registry import load_policy
from tests.policies.carp.factories import tiny_policy

VALIDATION_SEEDS = [200_000, 200_001, 200_002, 200_003]
TEST_SEEDS = [100_000, 100_001, 100_002]


def _run_dir(tmp_path, snapshot_epochs=(2, 4)):
    (tmp_path / "policy.pt").write_bytes(b"final")
    (tmp_path / "snapshots").mkdir()
    for epoch in snapshot_epochs:
        (tmp_path / "snapshots" / f"epoch{epoch:04d}.pt").write_bytes(b"snapshot")
    return tmp_path


def test_candidates_are_the_snapshots_and_the_final_policy_with_their_epochs_loss(tmp_path):
    losses = [0.9, 0.5, 0.4, 0.2, 0.3]
    candidates = find_candidates(_run_dir(tmp_path), losses)
    assert [(c.epoch, c.path.name, c.training_loss) for c in candidates] == [
        (2, "epoch0002.pt", 0.5),
        (4, "epoch0004.pt", 0.2),
        (5, "policy.pt", 0.3),
    ]


def test_a_missing_final_policy_or_a_snapshot_beyond_the_history_is_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match="no trained policy"):
        find_candidates(tmp_path, [0.5])
    _run_dir(tmp_path, snapshot_epochs=(7,))
    with pytest.raises(ValueError, match="epoch 7 lies outside the training history's 5 epochs"):
        find_candidates(tmp_path, [0.5] * 5)


CANDIDATES = [Candidate(2, "a", 0.5), Candidate(4, "b", 0.2), Candidate(5, "c", 0.2)]


def _scores(successes):
    return [CandidateScore(candidate, count, 10) for candidate, count in zip(CANDIDATES, successes)]


def test_each_rule_picks_its_candidate_and_ties_go_to_the_later_epoch():
    assert select_candidate(CANDIDATES, "final").chosen.epoch == 5
    assert select_candidate(CANDIDATES, "lowest_loss").chosen.epoch == 5  # 0.2 twice: the later one
    assert select_candidate(CANDIDATES, "best_validation", _scores([9, 6, 8])).chosen.epoch == 2
    assert select_candidate(CANDIDATES, "best_validation", _scores([7, 7, 3])).chosen.epoch == 4


def test_best_validation_without_scores_and_an_unknown_rule_are_refused():
    with pytest.raises(ValueError, match=r"best_validation needs validation episodes; epochs \[2, 4, 5\]"):
        select_candidate(CANDIDATES, "best_validation")
    with pytest.raises(ValueError, match="'best' must be one of"):
        select_candidate(CANDIDATES, "best")


def test_the_validation_summary_shows_the_optimistic_figures_beside_the_choice():
    selection = select_candidate(CANDIDATES, "final", _scores([9, 6, 8]))
    summary = selection.validation_summary(top_k=2)
    assert summary == {
        "selected_epoch": 5,
        "validation_max_success_rate": 0.9,
        "validation_top_k_mean_success_rate": pytest.approx(0.85),
        "validation_top_k": 2,
        "selected_validation_success_rate": 0.8,
    }
    assert select_candidate(CANDIDATES, "final").validation_summary(top_k=3) == {"selected_epoch": 5}


class RecordingEvaluator:
    """Runs no simulator: records every call and answers with fixed successes per checkpoint."""

    def __init__(self, successes_by_path):
        self.successes_by_path = successes_by_path
        self.calls = []

    def __call__(self, path, seeds):
        self.calls.append((path, list(seeds)))
        return [index < self.successes_by_path[path] for index in range(len(seeds))]


@pytest.mark.parametrize("rule", ["final", "best_validation", "lowest_loss"])
def test_no_test_seed_runs_before_the_checkpoint_is_fixed(rule):
    evaluator = RecordingEvaluator({"a": 4, "b": 1, "c": 2})
    evaluated = evaluate_with_selection(
        CANDIDATES, rule, evaluator, lambda outcome: outcome, VALIDATION_SEEDS, TEST_SEEDS
    )
    test_calls = [index for index, (_, seeds) in enumerate(evaluator.calls) if set(seeds) & set(TEST_SEEDS)]
    # One test evaluation, the last call, of the chosen checkpoint; every call before it used validation seeds only.
    assert test_calls == [len(evaluator.calls) - 1]
    assert evaluator.calls[-1] == (evaluated.selection.chosen.path, TEST_SEEDS)
    assert all(seeds == VALIDATION_SEEDS for _, seeds in evaluator.calls[:-1])
    assert [path for path, _ in evaluator.calls[:-1]] == ["a", "b", "c"]
    expected = {"final": "c", "best_validation": "a", "lowest_loss": "c"}[rule]
    assert evaluated.selection.chosen.path == expected
    assert evaluated.test == {"a": [True, True, True], "c": [True, True, False]}[expected]
    assert sorted(evaluated.validation) == [2, 4, 5]


def test_validation_alone_runs_no_test_seed_and_reports_each_candidate_as_it_finishes():
    evaluator = RecordingEvaluator({"a": 4, "b": 1, "c": 2})
    reported = []
    validated = validate_and_select(
        CANDIDATES,
        "best_validation",
        evaluator,
        lambda outcome: outcome,
        VALIDATION_SEEDS,
        on_validated=lambda candidate, outcome: reported.append((candidate.epoch, len(evaluator.calls), sum(outcome))),
    )
    assert all(seeds == VALIDATION_SEEDS for _, seeds in evaluator.calls)
    assert reported == [(2, 1, 4), (4, 2, 1), (5, 3, 2)]  # each one right after its own episodes, by epoch
    assert validated.selection.chosen.path == "a" and sorted(validated.validation) == [2, 4, 5]


def test_an_exception_from_the_validation_hook_stops_the_later_candidates():
    evaluator = RecordingEvaluator({"a": 4, "b": 1, "c": 2})

    def stop(candidate, outcome):
        raise RuntimeError(f"pruned at {candidate.epoch}")

    with pytest.raises(RuntimeError, match="pruned at 2"):
        evaluate_with_selection(
            CANDIDATES, "final", evaluator, lambda o: o, VALIDATION_SEEDS, TEST_SEEDS, on_validated=stop
        )
    assert evaluator.calls == [("a", VALIDATION_SEEDS)]


def test_a_validation_only_summary_names_its_figures_as_validation_and_has_no_test_figure():
    validation = {"score": 0.7, "success_rate": 0.6, "episodes": 10, "successes": 6, "latency_predict_ms_median": 2.0}
    summary = validation_only_summary((validation, []))
    assert summary == {
        "validation_score": 0.7,
        "validation_success_rate": 0.6,
        "validation_episodes": 10,
        "validation_successes": 6,
        "latency_predict_ms_median": 2.0,
        "test_episodes": 0,
    }
    with pytest.raises(ValueError, match="ran no test episode"):
        confirmed_checkpoint(CANDIDATES, {**summary, "selected_epoch": 2}, Path("."))


def test_without_validation_seeds_only_the_test_episodes_run():
    evaluator = RecordingEvaluator({"a": 4, "b": 1, "c": 2})
    evaluated = evaluate_with_selection(CANDIDATES, "final", evaluator, lambda outcome: outcome, [], TEST_SEEDS)
    assert evaluator.calls == [("c", TEST_SEEDS)]
    assert evaluated.validation == {} and evaluated.test == [True, True, False]


def test_overlapping_validation_and_test_seeds_are_refused_before_anything_runs():
    evaluator = RecordingEvaluator({"a": 4, "b": 1, "c": 2})
    with pytest.raises(ValueError, match=r"must be disjoint; both hold \[100001\]"):
        evaluate_with_selection(CANDIDATES, "final", evaluator, lambda o: o, [100_001, 200_000], TEST_SEEDS)
    assert evaluator.calls == []


def test_average_last_takes_the_latest_candidates_and_refuses_more_than_were_kept():
    selection = select_candidate(list(reversed(CANDIDATES)), "average_last", _scores([9, 6, 8]), average_last=2)
    assert [candidate.epoch for candidate in selection.averaged] == [4, 5] and selection.chosen.epoch == 5
    # No single candidate ran on the test seeds, so there is no selected candidate's validation figure.
    assert selection.validation_summary(top_k=1) == {
        "selected_epoch": 5,
        "averaged_checkpoints": 2,
        "validation_max_success_rate": 0.9,
        "validation_top_k_mean_success_rate": 0.9,
        "validation_top_k": 1,
    }
    with pytest.raises(ValueError, match=r"average_last=4: the training kept 3 candidates \(epochs \[2, 4, 5\]\)"):
        select_candidate(CANDIDATES, "average_last", average_last=4)


def test_the_averaged_policy_runs_on_the_test_seeds_after_validation_and_only_it():
    evaluator = RecordingEvaluator({"a": 4, "b": 1, "c": 2, "b+c": 3})
    averaged = []

    def average(candidates):
        averaged.append((len(evaluator.calls), [candidate.path for candidate in candidates]))
        return "b+c"

    evaluated = evaluate_with_selection(
        CANDIDATES, "average_last", evaluator, lambda outcome: outcome, VALIDATION_SEEDS, TEST_SEEDS, 2, average
    )
    assert averaged == [(3, ["b", "c"])]  # once, after the three validation runs
    assert evaluator.calls[-1] == ("b+c", TEST_SEEDS)
    assert [seeds for _, seeds in evaluator.calls[:-1]] == [VALIDATION_SEEDS] * 3
    assert str(evaluated.tested) == "b+c" and evaluated.test == [True, True, True]
    with pytest.raises(ValueError, match="needs a way to average"):
        evaluate_with_selection(CANDIDATES, "average_last", evaluator, lambda o: o, [], TEST_SEEDS, 2)


def _saved_run(directory):
    """A tiny CARP run whose transformer moves each epoch: snapshots after epochs 1 and 2, the final one after 3."""
    paths = [directory / "snapshots" / f"epoch{epoch:04d}.pt" for epoch in (1, 2)] + [directory / "policy.pt"]
    for epoch, path in enumerate(paths, start=1):
        policy = tiny_policy()
        with torch.no_grad():
            for parameter in policy.transformer.parameters():
                parameter.add_(float(epoch))
        policy.save(path)
    return find_candidates(directory, [0.5, 0.1, 0.3])


@pytest.mark.parametrize(
    ("rule", "validation_seeds", "selected_epoch"),
    [("final", [], 3), ("lowest_loss", [], 2), ("best_validation", VALIDATION_SEEDS, 1), ("average_last", [], 3)],
)
def test_the_confirmed_checkpoint_is_the_file_the_evaluation_ran_on_the_test_seeds(
    tmp_path, rule, validation_seeds, selected_epoch
):
    candidates = _saved_run(tmp_path / "run")
    evaluation_scratch, register_scratch = tmp_path / "evaluation", tmp_path / "register"
    evaluation_scratch.mkdir()
    register_scratch.mkdir()

    def run_episodes(path, seeds):
        # Only the first epoch's policy succeeds on the validation seeds, so best_validation picks an early snapshot.
        return [path == candidates[0].path and seeds != TEST_SEEDS] * len(seeds)

    evaluated = evaluate_with_selection(
        candidates,
        rule,
        run_episodes,
        lambda outcome: outcome,
        validation_seeds,
        TEST_SEEDS,
        average_last=2,
        average=lambda chosen: save_averaged_policy(chosen, evaluation_scratch / "averaged.pt"),
    )
    summary = evaluated.selection.validation_summary(top_k=1)
    assert summary["selected_epoch"] == selected_epoch

    checkpoint = confirmed_checkpoint(candidates, summary, register_scratch)
    assert checkpoint.read_bytes() == evaluated.tested.read_bytes()
    if rule == "average_last":
        assert checkpoint.parent == register_scratch
        assert load_policy(checkpoint).metadata["averaged_epochs"] == [2, 3]
        assert checkpoint.read_bytes() not in {candidate.path.read_bytes() for candidate in candidates}
    else:
        assert checkpoint == candidates[selected_epoch - 1].path


def test_a_summary_that_does_not_fit_the_run_names_what_is_missing(tmp_path):
    candidates = find_candidates(_run_dir(tmp_path), [0.9, 0.5, 0.4, 0.2, 0.3])
    with pytest.raises(ValueError, match="names no selected_epoch"):
        confirmed_checkpoint(candidates, {"success_rate": 0.5}, tmp_path)
    with pytest.raises(ValueError, match=r"selected epoch 3, which is not among the run's candidates \[2, 4, 5\]"):
        confirmed_checkpoint(candidates, {"selected_epoch": 3}, tmp_path)
    with pytest.raises(ValueError, match=r"averaged the last 3 candidates up to epoch 4, but the run holds 2"):
        confirmed_checkpoint(candidates, {"selected_epoch": 4, "averaged_checkpoints": 3}, tmp_path)
