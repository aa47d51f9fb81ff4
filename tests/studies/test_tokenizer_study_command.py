"""`pipeline/study.py tokenizers` and `tokenizer_reuse` as commands: refusals before any experiment, and (in
copies of the shared Lift pipeline) the tokenizers study over two kinds and the reuse study from Lift and Can to
Square, each run again without training anything, and the reuse walkthrough of docs/pipeline.md after it."""

import json
import sys

import pytest
import torch
import yaml

from carp.studies.data_efficiency import COMPLETE_MARKER
from carp.tracking.runs import find_runs
from tests.pipeline.shared_workspaces import copy_pipeline
from tests.pipeline.workspace import dvc, make_workspace, merge, run

# A workspace copy and a study process per test (20 s or more on a loaded 2-core CPU, minutes for the studies).
pytestmark = pytest.mark.slow


@pytest.mark.parametrize(
    ("study", "params", "message"),
    [
        (
            "tokenizers",
            {"policies": ["carp"]},
            "study.tokenizer_kinds: tokenizer kind binning: no family of policies=['carp'] is trained over its tokens",
        ),
        ("tokenizer_reuse", {"study": {"reuse_target_tasks": ["threading", "knitting"]}}, "unknown task 'knitting'"),
        ("tokenizer_reuse", {"study": {"reuse_target_tasks": ["pusht"]}}, "must share one action space"),
    ],
)
def test_the_study_command_refuses_before_any_experiment(tmp_path, study, params, message):
    workspace = make_workspace(tmp_path / "carp", params)
    completed = run([sys.executable, "pipeline/study.py", study], workspace, timeout=300)
    assert completed.returncode == 1
    last = completed.stderr.strip().splitlines()[-1]
    assert last.startswith(f"error: {workspace / 'params.yaml'}: study") and message in last
    assert not (workspace / "reports").exists()


def test_the_tokenizers_study_runs_each_kind_once_and_reports_it_against_carp_msvq(lift_pipeline, tmp_path):
    params = {
        "policies": ["carp", "next_token"],
        "next_token": {"depth": 1, "width": 16, "num_heads": 2, "warmup_steps": 2},
        "tokenizer_binning": {"bins": 16},
        "study": {"tokenizer_kinds": ["carp_msvq", "binning"], "replay_demos": 1},
    }
    workspace = copy_pipeline(lift_pipeline, tmp_path, params)
    params_before = (workspace / "params.yaml").read_text()
    first = run([sys.executable, "pipeline/study.py", "tokenizers"], workspace, timeout=1800)
    assert first.returncode == 0, first.stderr[-3000:]
    folder = workspace / "reports/studies/tokenizers"
    assert sorted(p.name for p in (folder / "binning/eval/lift").iterdir()) == ["next_token"]
    assert sorted(p.name for p in (folder / "carp_msvq/eval/lift").iterdir()) == ["carp", "next_token"]
    assert json.loads((folder / "binning/replay.json").read_text())["lift"]["demos"] == 1
    report = (folder / "report.md").read_text()
    assert "## Tokenizers study on lift" in report and "not decided (1 training seed)" in report
    assert (workspace / "params.yaml").read_text() == params_before
    finished = {kind: (folder / kind / COMPLETE_MARKER).stat().st_mtime_ns for kind in ("carp_msvq", "binning")}
    again = run([sys.executable, "pipeline/study.py", "tokenizers"], workspace, timeout=600)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stdout.strip().splitlines()[-1] == "wrote reports/studies/tokenizers/report.md"
    assert {kind: (folder / kind / COMPLETE_MARKER).stat().st_mtime_ns for kind in finished} == finished


def test_the_reuse_study_registers_the_source_tokenizer_once_and_runs_both_arms(lift_pipeline, tmp_path):
    # Lift and Can train the source tokenizer, Square reuses it: the walkthrough of docs/pipeline.md, whose plain
    # `dvc repro` form is the study's reused arm and whose own commands follow in the same workspace.
    params = {"study": {"reuse_source_tasks": ["lift", "can"], "reuse_target_tasks": ["square"], "replay_demos": 1}}
    workspace = copy_pipeline(lift_pipeline, tmp_path, {**params, "policies": ["carp"]})
    first = run([sys.executable, "pipeline/study.py", "tokenizer_reuse"], workspace, timeout=2400)
    assert first.returncode == 0, first.stderr[-3000:]
    folder = workspace / "reports/studies/tokenizer_reuse"
    source = json.loads((folder / "source/tokenizer_ref.json").read_text())
    assert (source["name"], source["alias"]) == ("carp-tokenizer-panda-abs10", "study-reuse-source")
    assert json.loads((folder / "source/tokenizer/tokenizer.json").read_text())["tasks"] == ["lift", "can"]
    for arm in ("own", "reused"):
        assert (folder / arm / "eval/square/carp/seed0.json").is_file()
    # The reused arm took the registered weights as they are and trained no tokenizer: its train_tokenizer stage
    # fetched the version and measured it on Square's held-out windows.
    reused = json.loads((folder / "reused/tokenizer/tokenizer.json").read_text())
    assert reused["tasks"] == ["lift", "can"] and reused["sha256"] == source["sha256"]
    assert json.loads((folder / "own/tokenizer/tokenizer.json").read_text())["tasks"] == ["square"]
    uri = f"models:/{source['name']}@{source['alias']}"
    (fetched,) = [
        r
        for r in find_runs(f"sqlite:///{workspace / 'mlflow.db'}", "carp-tokenizer")
        if r["tags"].get("carp.dvc_experiment") == "tokenizer_reuse-reused" and r["run_name"] == "train_tokenizer"
    ]
    assert fetched["tags"]["carp.tokenizer_source"] == uri and "train_loss" not in fetched["metrics"]
    assert "rmse_percent_range.mean" in fetched["metrics"]
    report = (folder / "report.md").read_text()
    assert "## Tokenizer reuse study on square" in report and "reused tokenizer" in report
    again = run([sys.executable, "pipeline/study.py", "tokenizer_reuse"], workspace, timeout=600)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stdout.strip().splitlines()[-1] == "wrote reports/studies/tokenizer_reuse/report.md"

    # The walkthrough's own commands in the same workspace (its params as before the study): Lift and Can's
    # tokenizer trained and registered, Square's data, then everything downstream of the registry stage, where
    # train_tokenizer is not even visited.
    set_params(workspace, tasks=["lift", "can"])
    registered = run(dvc("repro", "register_tokenizer"), workspace)
    assert registered.returncode == 0, registered.stderr[-3000:]
    reference = json.loads((workspace / "models/tokenizer_ref.json").read_text())
    assert (reference["name"], reference["alias"]) == ("carp-tokenizer-panda-abs10", "default")
    assert json.loads((workspace / "models/tokenizer/tokenizer.json").read_text())["tasks"] == ["lift", "can"]
    training_state = {p.name: p.stat().st_mtime_ns for p in (workspace / "checkpoints/tokenizer").iterdir()}
    set_params(workspace, tasks=["square"], tokenizer={"source": f"models:/{reference['name']}@default"})
    data = run(dvc("repro", "collect@square", "ingest@square"), workspace)
    assert data.returncode == 0, data.stderr[-3000:]
    downstream = run(dvc("repro", "--downstream", "register_tokenizer"), workspace)
    assert downstream.returncode == 0, downstream.stderr[-3000:]
    assert "'train_tokenizer'" not in data.stdout + downstream.stdout
    assert "Running stage 'train_policy@square-carp-0'" in downstream.stdout
    # The registered weights were used as they are: the same version and hash, in the Square policy's checkpoint too,
    # and the tokenizer's training state untouched.
    referenced = json.loads((workspace / "models/tokenizer_ref.json").read_text())
    assert (referenced["version"], referenced["sha256"]) == (reference["version"], reference["sha256"])
    checkpoint = torch.load(workspace / "models/policy/square/carp/seed0/policy.pt", weights_only=True)
    assert checkpoint["metadata"]["tokenizer"]["sha256"] == reference["sha256"]
    assert {p.name: p.stat().st_mtime_ns for p in (workspace / "checkpoints/tokenizer").iterdir()} == training_state
    # A registered tokenizer that does not fit the params is refused with the differing field named.
    set_params(workspace, codebook_size=32)
    refused = run(dvc("repro", "register_tokenizer"), workspace)
    assert refused.returncode != 0
    assert (
        "error: models:/carp-tokenizer-panda-abs10@default: tokenizer codebook_size is 16 but the params ask for 32"
        in refused.stderr.splitlines()
    ), refused.stderr[-2000:]


def set_params(workspace, **changes) -> None:
    """Merge ``changes`` into the workspace's params.yaml (nested mappings merged key by key)."""
    path = workspace / "params.yaml"
    path.write_text(yaml.safe_dump(merge(yaml.safe_load(path.read_text()), changes), sort_keys=False))
