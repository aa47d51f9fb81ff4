"""End to end: `dvc repro` on tiny params in a temporary copy of the repository, then a second run is a no-op.

The run is the shared arm pipeline (tests/pipeline/shared_workspaces.py, built once per test run), checked here in a
copy of its own. VQ-BeT trains and evaluates beside CARP there, so the one pipeline run also covers a family that no
other end-to-end test runs."""

import json
import re
import sys
from pathlib import Path

import h5py
import pytest
import yaml

from tests.pipeline.shared_workspaces import copy_pipeline
from tests.pipeline.workspace import run, stages_run
from tests.tools.test_import_graph import tool as import_graph


def _expanded_stages(workspace) -> list[str]:
    """Every stage instance of the workspace's pipeline (`collect@lift`, `train_policy@lift-carp-0`, ...)."""
    listed = run([sys.executable, "-m", "dvc", "stage", "list", "--name-only"], workspace)
    assert listed.returncode == 0, listed.stderr[-3000:]
    return listed.stdout.split()


def _stale_after(workspace, changed: str) -> set[str]:
    """The stages `dvc status` reports after a comment is appended to `changed` (the file is restored after)."""
    path = workspace / changed
    source = path.read_text()
    path.write_text(source + "\n# a change\n")
    try:
        status = run([sys.executable, "-m", "dvc", "status", "--json"], workspace)
    finally:
        path.write_text(source)
    return set(json.loads(status.stdout))


@pytest.mark.slow
def test_dvc_repro_runs_every_stage_and_second_run_is_a_no_op(lift_pipeline, tmp_path):
    # The shared pipeline's params (LIFT_PIPELINE): a task's entry in num_demos_per_task overrides num_demos (3 in the
    # tiny params) for its collection; its `dvc repro` ran every stage (the fixture fails if it did not).
    workspace = copy_pipeline(lift_pipeline, tmp_path)

    for output in (
        "data/inputs/lift.json",
        "data/raw/lift.hdf5",
        "data/processed/lift/replay.zarr",
        "data/processed/lift/normalization.json",
        "models/tokenizer/tokenizer.pt",
        "models/tokenizer_ref.json",
        "models/policy/lift/carp/seed0/policy.pt",
        "reports/tokenizer/metrics.json",
        "reports/tokenizer/reconstruction.png",
        "reports/policy/lift/carp/seed0/metrics.json",
        "reports/eval/lift/carp/seed0.json",
        "reports/eval/lift/carp/seed0_episodes.csv",
        "models/policy/lift/vq_bet/seed0/policy.pt",
        "reports/policy/lift/vq_bet/seed0/metrics.json",
        "reports/eval/lift/vq_bet/seed0.json",
        "reports/report.md",
        "reports/report.html",
    ):
        assert (workspace / output).exists(), output
    with h5py.File(workspace / "data/raw/lift.hdf5", "r") as raw:
        assert len(raw["data"]) == 4
    evaluation = json.loads((workspace / "reports/eval/lift/carp/seed0.json").read_text())
    assert evaluation["episodes"] == 2 and 0 <= evaluation["success_rate"] <= 1
    assert evaluation["latency_predict_ms_median"] > 0 and evaluation["top_k"] == 1
    reference = json.loads((workspace / "models/tokenizer_ref.json").read_text())
    assert reference["name"] == "carp-tokenizer-panda-abs10" and reference["alias"] == "default"
    assert (workspace / "mlflow.db").exists()
    vq_bet = json.loads((workspace / "reports/eval/lift/vq_bet/seed0.json").read_text())
    assert (vq_bet["policy_type"], vq_bet["episodes"], vq_bet["model_calls_per_chunk"]) == ("vq_bet", 2, 1)
    report = (workspace / "reports/report.md").read_text()
    assert "## Success rate" in report and "| vq_bet " in report

    second = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert second.returncode == 0, second.stderr[-3000:]
    # Only the always-run input check runs again; every stage that does work is up to date.
    assert stages_run(second.stdout) == {"check_inputs"}, second.stdout
    status = run([sys.executable, "-m", "dvc", "status", "--json"], workspace)
    assert json.loads(status.stdout) == {"check_inputs": ["always changed"]}, status.stdout

    # The token choice (top_k, or a task's entry in top_k_per_task) only changes decoding: evaluation and the report
    # are stale, the trained stages are not.
    params_file = workspace / "params.yaml"
    original = params_file.read_text()
    for section, value in (("top_k", 2), ("top_k_per_task", {"lift": 2})):
        params = yaml.safe_load(original)
        params["inference"]["carp"][section] = value
        params_file.write_text(yaml.safe_dump(params, sort_keys=False))
        status = run([sys.executable, "-m", "dvc", "status", "--json"], workspace)
        assert status.returncode == 0, status.stderr[-3000:]
        stale = set(json.loads(status.stdout))
        trained = [stage for stage in stale if stage.startswith("train_")]
        assert "evaluate@lift-carp-0" in stale and not trained, (section, stale)
    # A family's own section reaches its training alone.
    params = yaml.safe_load(original)
    params["vq_bet"]["offset_weight"] = 10.0
    params_file.write_text(yaml.safe_dump(params, sort_keys=False))
    status = run([sys.executable, "-m", "dvc", "status", "--json"], workspace)
    assert set(json.loads(status.stdout)) - {"check_inputs"} == {"train_policy@lift-vq_bet-0"}, status.stdout

    params_file.write_text(original)

    # A change to code makes exactly the stages that can run it stale (dvc.yaml's deps are derived from the imports,
    # tools/import_graph.py): the report's statistics reach the report alone, the training loop's settings every
    # stage that loads the params, CARP's trainer the stages that train or load CARP's policies.
    graph = import_graph.ImportGraph.build(workspace)
    scripts = import_graph.stage_scripts(workspace / "dvc.yaml")
    stages = [stage for stage in _expanded_stages(workspace) if stage != "check_inputs"]

    def reaching(changed: str) -> set[str]:
        return {stage for stage in stages if Path(changed) in graph.reached(scripts[stage.split("@")[0]][0])}

    assert reaching("src/carp/reporting/statistics.py") == {"report"}
    assert {"collect@lift", "ingest@lift", "train_policy@lift-carp-0"} <= reaching("src/carp/config/training.py")
    assert "train_policy@lift-carp-0" in reaching("src/carp/policies/carp/trainer.py")
    for changed in (
        "src/carp/reporting/statistics.py",
        "src/carp/config/training.py",
        "src/carp/policies/carp/trainer.py",
    ):
        assert _stale_after(workspace, changed) - {"check_inputs"} == reaching(changed), changed
    status = run([sys.executable, "-m", "dvc", "status", "--json"], workspace)
    assert json.loads(status.stdout) == {"check_inputs": ["always changed"]}, status.stdout

    # Inputs set back to values a stage has run with are restored from DVC's run cache, not run again: a CARP
    # training of other params, then the original params, restore the first policy and its evaluation.
    first_policy = (workspace / "models/policy/lift/carp/seed0/policy.pt").read_bytes()
    first_evaluation = (workspace / "reports/eval/lift/carp/seed0.json").read_text()
    first_episodes = (workspace / "reports/eval/lift/carp/seed0_episodes.csv").read_text()
    params = yaml.safe_load(original)
    params["carp"]["learning_rate"] = 3e-4
    params_file.write_text(yaml.safe_dump(params, sort_keys=False))
    other = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert other.returncode == 0, other.stderr[-3000:]
    assert {"train_policy@lift-carp-0", "evaluate@lift-carp-0"} <= stages_run(other.stdout), other.stdout
    assert (workspace / "models/policy/lift/carp/seed0/policy.pt").read_bytes() != first_policy
    params_file.write_text(original)
    back = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert back.returncode == 0, back.stderr[-3000:]
    restored = set(re.findall(r"Stage '([^']+)' is cached - skipping run", back.stdout))
    assert {"train_policy@lift-carp-0", "evaluate@lift-carp-0"} <= restored, back.stdout
    assert stages_run(back.stdout) == {"check_inputs", "report"}, back.stdout
    assert (workspace / "models/policy/lift/carp/seed0/policy.pt").read_bytes() == first_policy
    assert (workspace / "reports/eval/lift/carp/seed0.json").read_text() == first_evaluation
    assert (workspace / "reports/eval/lift/carp/seed0_episodes.csv").read_text() == first_episodes
    # The per-epoch and per-episode tables are the stages' plots.
    plots = run([sys.executable, "-m", "dvc", "plots", "show", "--json"], workspace)
    assert plots.returncode == 0, plots.stderr[-3000:]
    assert "reports/policy/lift/carp/seed0/history.csv" in plots.stdout, plots.stdout[:3000]
