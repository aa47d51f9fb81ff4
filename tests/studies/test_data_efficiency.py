"""The data-efficiency study: one experiment per size, each size's evaluation kept, resumed, and reported."""

import json
import re
import sys

import numpy as np
import pandas as pd
import pytest

from carp.reporting.comparison import decide_groups, family_pairs
from carp.reporting.runs import RunResults
from carp.studies.data_efficiency import (
    StudyLayout,
    add_referenced_studies,
    claims_table,
    experiment_overrides,
    run_study,
    summary_path,
    write_study_report,
)
from tests.pipeline.workspace import make_workspace, run

LAYOUT = StudyLayout(tasks=("lift",), policies=("carp", "diffusion_unet"), seeds=(0, 1, 2))
SIZES = (30, 60, 100)
EPISODES = 150


class FakeExperiments:
    """Stands in for `dvc exp run`: writes each (task, family, seed)'s evaluation as the evaluate stage would.

    Success grows with the demo count, faster for carp, so the study has something to show.
    """

    def __init__(self, eval_dir, fail_at=None, families=LAYOUT.policies):
        self.eval_dir = eval_dir
        self.fail_at = fail_at
        self.families = families
        self.calls = []

    def __call__(self, name, overrides):
        self.calls.append((name, overrides))
        size = int(overrides[1].split("=")[1])
        if size == self.fail_at:
            raise RuntimeError(f"experiment {name} failed")
        for index, (family, scale) in enumerate((("carp", 1.0), ("diffusion_unet", 0.6))):
            if family not in self.families:
                continue
            # One stream per family, so that a family's episodes do not depend on which others run beside it.
            generator = np.random.default_rng([size, index])
            for seed in LAYOUT.seeds:
                rate = min(0.95, scale * size / 100)
                success = generator.random(EPISODES) < rate
                summary = summary_path(self.eval_dir, "lift", family, seed)
                summary.parent.mkdir(parents=True, exist_ok=True)
                summary.write_text(json.dumps({"successes": int(success.sum()), "episodes": EPISODES}))
                pd.DataFrame(
                    {"seed": 100_000 + np.arange(EPISODES), "success": success, "steps": np.where(success, 80, 400)}
                ).to_csv(summary.with_name(f"{summary.stem}_episodes.csv"), index=False)


def test_every_size_collects_the_largest_file_and_ingests_its_subset():
    assert experiment_overrides(60, SIZES) == ["data.num_demos=100", "data.subset_size=60"]


def test_each_size_runs_once_and_an_interrupted_study_resumes_at_the_missing_size(tmp_path):
    eval_dir, output = tmp_path / "reports/eval", tmp_path / "study"
    failing = FakeExperiments(eval_dir, fail_at=100)
    with pytest.raises(RuntimeError, match="data-efficiency-100 failed"):
        run_study(SIZES, LAYOUT, eval_dir, output, failing)
    assert [name for name, _ in failing.calls] == ["data-efficiency-30", "data-efficiency-60", "data-efficiency-100"]
    assert sorted(path.name for path in output.iterdir()) == ["size30", "size60"]

    resumed = FakeExperiments(eval_dir)
    points = run_study(SIZES, LAYOUT, eval_dir, output, resumed)
    assert [name for name, _ in resumed.calls] == ["data-efficiency-100"]
    assert sorted(points) == list(SIZES)
    # Each size keeps its own copy: the 30-demo results are not the workspace's latest ones.
    thirty = points[30]["lift"]["carp"][0].metrics["successes"]
    hundred = points[100]["lift"]["carp"][0].metrics["successes"]
    assert thirty < hundred

    # Another layout (a third seed) is not the same study: every size runs again.
    wider = StudyLayout(LAYOUT.tasks, LAYOUT.policies, (0, 1, 2, 3))
    again = FakeExperiments(eval_dir)
    with pytest.raises(FileNotFoundError, match="seed3.json: the experiment of size 30 left no evaluation here"):
        run_study(SIZES, wider, eval_dir, output, again)


def test_the_report_shows_each_familys_curve_and_the_verdicts_per_size(tmp_path):
    eval_dir, output = tmp_path / "reports/eval", tmp_path / "study"
    points = run_study(SIZES, LAYOUT, eval_dir, output, FakeExperiments(eval_dir))
    markdown = write_study_report(points, margin=0.05, alpha=0.05, output_dir=output).read_text()
    assert "## Data efficiency on lift" in markdown
    assert (output / "figures" / "data_efficiency_lift.png").stat().st_size > 0
    for size in SIZES:
        assert f"{size} demos, " in markdown
    # At 100 demos carp (95%) against diffusion_unet (60%) over 3 seeds of 150 paired episodes is decided.
    assert "100 demos, carp better" in markdown
    # carp is ahead at every size, but 30% against 18% over 3 seeds of 150 episodes is not decided under the
    # study's correction, so the paper's claim stays open.
    assert re.search(
        r"\| CARP's success is higher than diffusion_unet's at every number of demos +\| not decided +\| 30 demos: "
        r"[0-9.]+% against [0-9.]+%, not decided;",
        markdown,
    )


def test_a_study_split_by_family_over_two_folders_is_reported_as_one(tmp_path):
    eval_dir = tmp_path / "reports/eval"
    whole = run_study(SIZES, LAYOUT, eval_dir, tmp_path / "whole", FakeExperiments(eval_dir))
    halves = {}
    for family in LAYOUT.policies:
        layout = StudyLayout(LAYOUT.tasks, (family,), LAYOUT.seeds)
        folder = tmp_path / f"clone-{family}"
        halves[family] = run_study(SIZES, layout, eval_dir, folder, FakeExperiments(eval_dir, families=(family,)))
    merged, notes = add_referenced_studies(halves["carp"], {"clone-dp": tmp_path / "clone-diffusion_unet"}, ["lift"])
    assert notes == {
        "lift": "Evaluations of other runs (study.references): diffusion_unet (training seeds 0, 1, 2) from clone-dp."
    }
    for size in SIZES:
        assert sorted(merged[size]["lift"]) == ["carp", "diffusion_unet"]
        for family in LAYOUT.policies:
            for seed in LAYOUT.seeds:
                ours, theirs = merged[size]["lift"][family][seed], whole[size]["lift"][family][seed]
                assert ours.metrics == theirs.metrics
                pd.testing.assert_frame_equal(ours.episodes, theirs.episodes)
    output = tmp_path / "combined"
    markdown = write_study_report(merged, margin=0.05, alpha=0.05, output_dir=output, reference_notes=notes).read_text()
    assert "diffusion_unet (training seeds 0, 1, 2) from clone-dp" in markdown
    assert "100 demos, carp better" in markdown

    # A reference without one of the sizes, or with a family's seed the study has already, is refused.
    with pytest.raises(FileNotFoundError, match="size200: no finished evaluation of 200 demos in clone-dp"):
        add_referenced_studies(
            {**halves["carp"], 200: halves["carp"][100]}, {"clone-dp": tmp_path / "clone-diffusion_unet"}, ["lift"]
        )
    with pytest.raises(ValueError, match="clone-carp: lift/carp training seed 0 is already in the report"):
        add_referenced_studies(halves["carp"], {"clone-carp": tmp_path / "clone-carp"}, ["lift"])


def test_the_study_command_refuses_a_missing_reference_before_any_experiment(tmp_path):
    workspace = make_workspace(tmp_path / "carp", {"study": {"references": ["results/no-such-study"]}})
    params_before = (workspace / "params.yaml").read_text()
    completed = run([sys.executable, "pipeline/study.py", "data_efficiency"], workspace, timeout=300)
    assert completed.returncode == 1
    assert completed.stderr.strip().splitlines()[-1] == (
        f"error: {workspace / 'params.yaml'}: study.references: results/no-such-study: no such study folder"
    )
    assert (workspace / "params.yaml").read_text() == params_before
    assert not (workspace / "reports").exists()


def simulated_sizes(rates_by_size, episodes=400, seeds=(0, 1, 2)):
    """size -> pair comparisons on "square", decided under one correction as the study does: each episode succeeds
    with its family's rate at that size."""
    points = {}
    for size, rates in rates_by_size.items():
        families = {}
        for index, (family, rate) in enumerate(rates.items()):
            generator = np.random.default_rng([size, index])
            runs = {}
            for seed in seeds:
                success = generator.random(episodes) < rate
                episodes_table = pd.DataFrame(
                    {"seed": 100_000 + np.arange(episodes), "success": success, "steps": np.where(success, 150, 400)}
                )
                runs[seed] = RunResults({"successes": int(success.sum()), "episodes": episodes}, episodes_table)
            families[family] = runs
        points[size] = {"square": families}
    groups = [(["square"], family_pairs(point)) for point in points.values()]
    return dict(zip(points, decide_groups(groups, margin=0.05, alpha=0.05)))


@pytest.mark.parametrize(
    ("rates_by_size", "expected"),
    [
        # Ahead by 30 points at both sizes over 400 paired episodes each: decided both times.
        ({30: {"carp": 0.5, "diffusion_unet": 0.2}, 100: {"carp": 0.9, "diffusion_unet": 0.6}}, "holds"),
        # The baseline ahead at the small size: one "worse" is enough to refute "at every size".
        ({30: {"carp": 0.2, "diffusion_unet": 0.5}, 100: {"carp": 0.9, "diffusion_unet": 0.6}}, "does not hold"),
        # Both solve every episode at 100 demos: on par within the margin is not "higher".
        ({30: {"carp": 0.5, "diffusion_unet": 0.2}, 100: {"carp": 1.0, "diffusion_unet": 1.0}}, "does not hold"),
        # One point apart at 100 demos settles neither way.
        ({30: {"carp": 0.5, "diffusion_unet": 0.2}, 100: {"carp": 0.61, "diffusion_unet": 0.6}}, "not decided"),
    ],
)
def test_the_data_efficiency_claim_holds_only_where_carp_is_better_at_every_size(rates_by_size, expected):
    claims = claims_table(simulated_sizes(rates_by_size), "square")
    assert list(claims["claim"]) == ["CARP's success is higher than diffusion_unet's at every number of demos"]
    assert list(claims["verdict"]) == [expected]
    evidence = claims["evidence"].item()
    assert evidence.startswith("30 demos: ") and "; 100 demos: " in evidence


def test_one_training_seed_per_size_never_makes_the_claim_hold():
    rates = {30: {"carp": 0.5, "diffusion_unet": 0.2}, 100: {"carp": 0.9, "diffusion_unet": 0.6}}
    claims = claims_table(simulated_sizes(rates, seeds=(0,)), "square")
    assert list(claims["verdict"]) == ["not decided"]
    assert "not decided (1 training seed)" in claims["evidence"].item()


def test_the_claim_is_checked_against_every_baseline_and_only_with_carp_in_the_study():
    rates = {"carp": 0.9, "diffusion_unet": 0.5, "next_token": 0.88}
    claims = claims_table(simulated_sizes({30: rates, 100: rates}), "square")
    assert list(claims["verdict"]) == ["holds", "not decided"]
    assert claims["claim"].str.contains("diffusion_unet|next_token").all()
    without_carp = simulated_sizes(
        {30: {"diffusion_unet": 0.5, "next_token": 0.8}, 100: {"diffusion_unet": 0.5, "next_token": 0.8}}
    )
    assert claims_table(without_carp, "square").empty
