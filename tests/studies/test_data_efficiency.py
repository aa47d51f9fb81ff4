"""The data-efficiency study: one experiment per size, each size's evaluation kept, resumed, and reported."""

import json

import numpy as np
import pandas as pd
import pytest

from carp.studies.data_efficiency import (
    StudyLayout,
    experiment_overrides,
    run_study,
    summary_path,
    write_study_report,
)

LAYOUT = StudyLayout(tasks=("lift",), policies=("carp", "diffusion_unet"), seeds=(0, 1, 2))
SIZES = (30, 60, 100)
EPISODES = 150


class FakeExperiments:
    """Stands in for `dvc exp run`: writes each (task, family, seed)'s evaluation as the evaluate stage would.

    Success grows with the demo count, faster for carp, so the study has something to show.
    """

    def __init__(self, eval_dir, fail_at=None):
        self.eval_dir = eval_dir
        self.fail_at = fail_at
        self.calls = []

    def __call__(self, name, overrides):
        self.calls.append((name, overrides))
        size = int(overrides[1].split("=")[1])
        if size == self.fail_at:
            raise RuntimeError(f"experiment {name} failed")
        generator = np.random.default_rng(size)
        for family, scale in (("carp", 1.0), ("diffusion_unet", 0.6)):
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
