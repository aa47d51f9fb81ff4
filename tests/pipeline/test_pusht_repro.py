"""End to end on Push-T: `dvc repro` with `tasks: [pusht]` on tiny params collects with the planning expert, ingests
2-D targets, trains a tokenizer and CARP (with VQ-BeT and Consistency Policy beside it) in Push-T's action space,
evaluates with DP's score and a video, reports them with the scripted-demo caveat, and a second run does nothing.

The run is the shared Push-T pipeline (tests/pipeline/shared_workspaces.py, built once per test run), checked here in
a copy of its own."""

import json
import sys

import pandas as pd
import pytest

from tests.pipeline.shared_workspaces import copy_pipeline
from tests.pipeline.workspace import run, stages_run


@pytest.mark.slow
def test_push_t_runs_through_every_stage_and_a_second_run_does_nothing(pusht_pipeline, tmp_path):
    # The shared pipeline's params (PUSHT_PIPELINE): the two families whose tokenizer and teacher are their own
    # (VQ-BeT's residual VQ-VAE, Consistency Policy's EDM teacher) run beside CARP, at the sizes of their own e2e
    # tests; its `dvc repro` ran every stage (the fixture fails if it did not).
    workspace = copy_pipeline(pusht_pipeline, tmp_path)
    for output in (
        "data/raw/pusht.hdf5",
        "data/processed/pusht/replay.zarr",
        "models/tokenizer",
        "models/policy/pusht/carp/seed0/policy.pt",
        "reports/eval/pusht/carp/seed0.json",
        "reports/eval/videos",
        "reports/report.md",
    ):
        assert (workspace / output).exists(), output
    processed = json.loads((workspace / "data/processed/pusht/summary.json").read_text())
    assert (processed["obs_dim"], processed["action_dim"], processed["episodes"]) == (20, 2, 3)
    tokenizer_metrics = json.loads((workspace / "reports/tokenizer/metrics.json").read_text())
    assert {"mse/target_x", "mse/target_y"} <= set(tokenizer_metrics)
    tokenizer_ref = json.loads((workspace / "models/tokenizer_ref.json").read_text())
    assert "pusht-abs2" in json.dumps(tokenizer_ref)
    summary = json.loads((workspace / "reports/eval/pusht/carp/seed0.json").read_text())
    assert summary["episodes"] == 2 and summary["max_reward_episodes"] == 2
    assert 0.0 <= summary["max_reward_mean"] <= 1.0
    assert summary["score"] == summary["max_reward_mean"]  # what a sweep over Push-T maximizes
    for family in ("vq_bet", "consistency_policy"):
        other = json.loads((workspace / f"reports/eval/pusht/{family}/seed0.json").read_text())
        assert other["max_reward_episodes"] == 2 and other["score"] == other["max_reward_mean"], family
    episodes = pd.read_csv(workspace / "reports/eval/pusht/carp/seed0_episodes.csv")
    assert set(episodes["seed"]) == {100_000, 100_001} and (episodes["steps"] <= 30).all()
    assert episodes["max_reward"].between(0, 1).all()
    assert list((workspace / "reports/eval/videos").glob("pusht_carp-0*.gif"))
    report = (workspace / "reports/report.md").read_text()
    assert "The pusht demos are scripted by carp's expert (pusht_planner), not Diffusion Policy's human" in report
    assert "| max_reward " in report

    second = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert second.returncode == 0, second.stderr[-3000:]
    assert stages_run(second.stdout) == {"check_inputs"}, second.stdout
