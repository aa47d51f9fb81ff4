"""A task without a simulator through `dvc repro`: a LeRobotDataset named under a task name carp does not know trains
every listed family and is evaluated offline (action errors on the held-out episode), and the report says that no
rollout was possible. The v3.0 fixture runs every stage; the v2.1 fixture (the same frames, LeRobot 0.3.3's writer)
then reruns only the input stages, as its replay buffer is the same, so training and evaluation stand for both. A
duel, which rolls policies out, refuses such a task."""

import json
import sys

import pandas as pd
import pytest
import yaml

from tests.pipeline.workspace import REPO, make_workspace, run, stages_run

OFFLINE = {
    "tasks": ["my_robot"],
    "policies": ["carp", "diffusion_transformer"],
    "seeds": [0],
    "data": {"raw_files": {"my_robot": "tests/fixtures/lerobot/v3.0"}},
    "diffusion_transformer": {"num_layers": 1, "num_heads": 2, "width": 16, "num_train_steps": 10, "warmup_steps": 2},
    "inference": {"diffusion_transformer": {"sampler": "ddim", "num_inference_steps": 2}},
}


def repro(workspace):
    result = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert result.returncode == 0, result.stderr[-3000:] + result.stdout[-3000:]
    return stages_run(result.stdout)


def ingest_outputs(workspace):
    lock = yaml.safe_load((workspace / "dvc.lock").read_text())
    return {out["path"]: out["md5"] for out in lock["stages"]["ingest@my_robot"]["outs"]}


@pytest.mark.slow
def test_a_lerobot_dataset_without_a_simulator_trains_and_is_evaluated_offline(tmp_path):
    workspace = make_workspace(tmp_path / "carp", OFFLINE)
    ran = repro(workspace)
    assert {"train_policy@my_robot-carp-0", "evaluate@my_robot-diffusion_transformer-0", "report"} <= ran

    processed = json.loads((workspace / "data/processed/my_robot/summary.json").read_text())
    assert (processed["obs_dim"], processed["action_dim"], processed["episodes"]) == (6, 2, 3)
    assert processed["valid_episodes"] == 1
    for family in OFFLINE["policies"]:
        for seed in OFFLINE["seeds"]:
            report = workspace / f"reports/eval/my_robot/{family}/seed{seed}.json"
            summary = json.loads(report.read_text())
            assert summary["evaluation"] == "offline" and summary["held_out_episodes"] == 1
            assert "success_rate" not in summary
            steps = [summary[f"step_rmse/{step}"] for step in range(16)]
            dimensions = [summary["dimension_rmse/x"], summary["dimension_rmse/y"]]
            # The whole chunk's RMSE is the root of the mean of the per-step (and per-dimension) mean squares.
            assert summary["action_rmse"] == pytest.approx(sum(value**2 for value in steps) ** 0.5 / 4)
            assert summary["action_rmse"] == pytest.approx((sum(value**2 for value in dimensions) / 2) ** 0.5)
            episodes = pd.read_csv(report.with_name(f"seed{seed}_episodes.csv"))
            # The held-out episode is the last of the three (15 steps); its windows start To - 1 = 1 step before it and
            # run until their executed rows reach its last step: starts -1 to 6.
            assert episodes[["episode", "steps", "windows"]].values.tolist() == [[2, 15, 8]]
            assert pd.read_csv(report.with_name(f"seed{seed}_validation.csv")).empty
    markdown = (workspace / "reports/report.md").read_text()
    assert "## Offline evaluation on my_robot" in markdown and "No rollout was possible" in markdown
    assert "## Success rate" not in markdown
    assert repro(workspace) == {"check_inputs"}  # a second run does nothing

    from_v3 = ingest_outputs(workspace)
    params = yaml.safe_load((workspace / "params.yaml").read_text())
    params["data"]["raw_files"]["my_robot"] = "tests/fixtures/lerobot/v2.1"
    (workspace / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    assert repro(workspace) == {"check_inputs", "collect@my_robot", "ingest@my_robot"}
    assert ingest_outputs(workspace) == from_v3
    assert repro(workspace) == {"check_inputs"}


def test_a_duel_on_a_task_without_a_simulator_is_refused_in_one_line(tmp_path):
    params_file = tmp_path / "params.yaml"
    dataset = REPO / "tests/fixtures/lerobot/v3.0"
    params_file.write_text(yaml.safe_dump({"tasks": ["my_robot"], "data": {"raw_files": {"my_robot": str(dataset)}}}))
    duel = [sys.executable, "pipeline/duel.py", "--params", str(params_file), "--task", "my_robot"]
    refused = run([*duel, "--first", "carp", "--second", "carp"], REPO, timeout=120)
    assert refused.returncode == 1
    assert refused.stderr.splitlines() == [
        f"error: {params_file}: tasks=['my_robot']: my_robot has no simulator, and a duel rolls policies out (the "
        "report compares its families offline)"
    ]
