"""End to end on tiny params: `dvc exp run -S` in the workspace, queued and with --temp.

Every test works in its own copy of the module's template workspace (`template`, tests/pipeline/conftest.py).
"""

import pytest

from tests.pipeline.experiment_workspaces import TRIAL_TIMEOUT_SECONDS, copy_workspace, experiments, head, mlflow_runs
from tests.pipeline.workspace import dvc, run


@pytest.mark.slow
def test_invalid_set_values_are_refused_with_one_line(template, tmp_path):
    workspace = copy_workspace(template, tmp_path)
    for value, message in (
        ("codebook_size=1", "codebook_size=1: must be >= 2"),
        ("scales=[1,2,3]", "scales=[1, 2, 3]: must end at the latent length l = "),
    ):
        refused = run(dvc("exp", "run", "-S", value), workspace)
        assert refused.returncode != 0
        errors = [line for line in (refused.stdout + refused.stderr).splitlines() if line.startswith("error: ")]
        assert len(errors) == 1 and message in errors[0], refused.stdout[-2000:] + refused.stderr[-2000:]
        assert run(["git", "checkout", "--", "params.yaml"], workspace).returncode == 0
    assert experiments(workspace) == {}


@pytest.mark.slow
def test_two_queued_experiments_run_at_once_on_a_fresh_store_keep_every_run(template, tmp_path):
    # No mlflow.db yet: both workers' first stages open a store that does not exist (the schema-creation race).
    workspace = copy_workspace(template, tmp_path)
    assert not (workspace / "mlflow.db").exists()
    sizes = {"tiny-a": 8, "tiny-b": 16}
    for name, size in sizes.items():
        queued = run(dvc("exp", "run", "--queue", "-n", name, "-S", f"codebook_size={size}"), workspace)
        assert queued.returncode == 0, queued.stderr[-3000:]
    completed = run(dvc("exp", "run", "--run-all", "--jobs", "2"), workspace, timeout=2 * TRIAL_TIMEOUT_SECONDS)
    assert completed.returncode == 0, completed.stderr[-3000:]

    shown = experiments(workspace)
    assert set(shown) == set(sizes), run(dvc("queue", "status"), workspace).stdout
    stages = {"train_tokenizer", "register_tokenizer", "train_policy@lift-carp-0", "evaluate@lift-carp-0"}
    for name, size in sizes.items():
        assert isinstance(shown[name]["metrics"]["success_rate"], float), name
        tagged = [r for r in mlflow_runs(workspace) if r.data.tags.get("carp.dvc_experiment") == name]
        assert sorted(r.data.tags["carp.dvc_stage"] for r in tagged) == sorted(stages), name
        assert {r.info.status for r in tagged} == {"FINISHED"}, name
        assert {r.data.params["codebook_size"] for r in tagged} == {str(size)}, name


@pytest.mark.slow
def test_temp_experiment_lands_in_the_workspace_store_with_its_name(template, tmp_path):
    workspace = copy_workspace(template, tmp_path)
    params_before = (workspace / "params.yaml").read_text()
    command = dvc("exp", "run", "--temp", "-n", "tiny-temp", "-S", "scales=[2,4]", "-S", "codebook_size=8")
    completed = run(command, workspace)
    assert completed.returncode == 0, completed.stderr[-3000:]
    assert (workspace / "params.yaml").read_text() == params_before  # --temp leaves the workspace alone

    tagged = [r for r in mlflow_runs(workspace) if r.data.tags.get("carp.dvc_experiment") == "tiny-temp"]
    stages = {r.data.tags["carp.dvc_stage"] for r in tagged}
    assert stages == {"train_tokenizer", "register_tokenizer", "train_policy@lift-carp-0", "evaluate@lift-carp-0"}
    assert {r.data.tags["carp.git_commit"] for r in tagged} == {head(workspace)}
    assert {r.data.params["codebook_size"] for r in tagged} == {"8"}
    for r in tagged:
        assert r.info.artifact_uri.startswith((workspace / "mlartifacts").as_uri())
    assert not list((workspace / ".dvc" / "tmp").rglob("mlflow.db"))

    shown = experiments(workspace)["tiny-temp"]
    assert shown["params"]["scales"] == [2, 4] and shown["params"]["codebook_size"] == 8
    for metric in ("success_rate", "rmse_percent_range/mean", "latency_predict_ms_median", "latency_decode_ms_median"):
        assert isinstance(shown["metrics"][metric], float), metric
