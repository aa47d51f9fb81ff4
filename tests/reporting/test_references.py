"""Evaluations of other runs in the report (`comparison.references`): reading another run's tree and merging seeds."""

import json

import pandas as pd
import pytest

from carp.reporting.runs import (
    RunResults,
    add_referenced_runs,
    merge_runs,
    read_run_results,
    referenced_runs,
    split_multitask,
)


def _write_evaluation(eval_dir, task: str, label: str, seed: int, successes: list[bool]) -> None:
    folder = eval_dir / task / label
    folder.mkdir(parents=True, exist_ok=True)
    summary = {"episodes": len(successes), "successes": sum(successes), "training_seed": seed}
    (folder / f"seed{seed}.json").write_text(json.dumps(summary))
    episodes = pd.DataFrame({"seed": range(100, 100 + len(successes)), "success": successes, "steps": 50})
    episodes.to_csv(folder / f"seed{seed}_episodes.csv", index=False)


def test_another_runs_tree_is_read_per_task_label_and_seed_and_other_files_are_ignored(tmp_path):
    eval_dir = tmp_path / "earlier" / "eval"
    _write_evaluation(eval_dir, "lift", "carp", 1, [True, False])
    _write_evaluation(eval_dir, "lift", "carp", 2, [True, True])
    _write_evaluation(eval_dir, "lift", "carp-multitask", 0, [False, False])
    _write_evaluation(eval_dir, "square", "carp", 0, [True])
    (eval_dir / "lift" / "carp" / "seed1_validation.csv").write_text("epoch,seed,success\n")
    (eval_dir / "lift" / "videos").mkdir()
    found = referenced_runs(eval_dir, ["lift", "can"])
    assert list(found) == ["lift"]  # square is not one of the run's tasks, can has no evaluation there
    assert {label: sorted(runs) for label, runs in found["lift"].items()} == {"carp": [1, 2], "carp-multitask": [0]}
    run = found["lift"]["carp"][1]
    assert run.metrics["successes"] == 1 and run.episodes["success"].tolist() == [True, False]


def test_seeds_add_up_and_a_seed_from_two_places_is_refused_naming_them(tmp_path):
    eval_dir = tmp_path / "eval"
    _write_evaluation(eval_dir, "lift", "carp", 0, [True])
    own_run = read_run_results(eval_dir / "lift" / "carp" / "seed0.json")
    own = {"lift": {"carp": {0: own_run}}}
    other = RunResults({"episodes": 1, "successes": 0}, pd.DataFrame({"seed": [100], "success": [False]}))
    merged = merge_runs(own, {"lift": {"carp": {1: other}, "next_token": {0: other}}}, "results/earlier")
    assert sorted(merged["lift"]["carp"]) == [0, 1] and list(merged["lift"]["next_token"]) == [0]
    assert list(own["lift"]["carp"]) == [0]  # the run's own mapping is left as it was
    with pytest.raises(ValueError, match="results/earlier: lift/carp training seed 0 is already in the report"):
        merge_runs(own, {"lift": {"carp": {0: other}}}, "results/earlier")


def test_a_missing_directory_or_episodes_file_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such evaluation directory"):
        referenced_runs(tmp_path / "absent", ["lift"])
    _write_evaluation(tmp_path / "eval", "lift", "carp", 3, [True])
    (tmp_path / "eval" / "lift" / "carp" / "seed3_episodes.csv").unlink()
    with pytest.raises(FileNotFoundError, match="seed3.json: no seed3_episodes.csv beside it"):
        referenced_runs(tmp_path / "eval", ["lift"])


def test_referenced_evaluations_are_added_with_a_note_of_where_they_came_from(tmp_path):
    _write_evaluation(tmp_path / "a", "lift", "carp", 1, [True])
    _write_evaluation(tmp_path / "a", "lift", "carp-multitask", 0, [False])
    _write_evaluation(tmp_path / "b", "lift", "next_token", 0, [True])
    own = {"lift": {"carp": {0: read_run_results(tmp_path / "a" / "lift" / "carp" / "seed1.json")}}}
    merged, notes = add_referenced_runs(own, {"results/a": tmp_path / "a", "results/b": tmp_path / "b"}, ["lift"])
    assert {label: sorted(runs) for label, runs in merged["lift"].items()} == {
        "carp": [0, 1],
        "carp-multitask": [0],
        "next_token": [0],
    }
    assert notes == {
        "lift": "Evaluations of other runs (comparison.references): carp (training seeds 1) from results/a; "
        "carp-multitask (training seeds 0) from results/a; next_token (training seeds 0) from results/b."
    }
    single, multi = split_multitask(merged, "-multitask")
    assert sorted(single["lift"]) == ["carp", "next_token"] and list(multi) == ["lift"]
    assert list(multi["lift"]) == ["carp"] and list(multi["lift"]["carp"]) == [0]
    assert split_multitask(own, "-multitask")[1] == {}
