"""`pipeline/study.py tokenizers` and `tokenizer_reuse` as commands: refusals before any experiment, and (in
copies of the shared Lift pipeline) the tokenizers study over two kinds and the reuse study from Lift to Can, each
run again without training anything."""

import json
import sys

import pytest

from carp.studies.data_efficiency import COMPLETE_MARKER
from tests.pipeline.shared_workspaces import copy_pipeline
from tests.pipeline.workspace import make_workspace, run

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
    params = {"study": {"reuse_source_tasks": ["lift"], "reuse_target_tasks": ["can"], "replay_demos": 1}}
    workspace = copy_pipeline(lift_pipeline, tmp_path, {**params, "policies": ["carp"]})
    first = run([sys.executable, "pipeline/study.py", "tokenizer_reuse"], workspace, timeout=2400)
    assert first.returncode == 0, first.stderr[-3000:]
    folder = workspace / "reports/studies/tokenizer_reuse"
    source = json.loads((folder / "source/tokenizer_ref.json").read_text())
    assert source["alias"] == "study-reuse-source"
    assert json.loads((folder / "source/tokenizer/tokenizer.json").read_text())["tasks"] == ["lift"]
    for arm in ("own", "reused"):
        assert (folder / arm / "eval/can/carp/seed0.json").is_file()
    assert json.loads((folder / "reused/tokenizer/tokenizer.json").read_text())["tasks"] == ["lift"]
    assert json.loads((folder / "own/tokenizer/tokenizer.json").read_text())["tasks"] == ["can"]
    report = (folder / "report.md").read_text()
    assert "## Tokenizer reuse study on can" in report and "reused tokenizer" in report
    again = run([sys.executable, "pipeline/study.py", "tokenizer_reuse"], workspace, timeout=600)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stdout.strip().splitlines()[-1] == "wrote reports/studies/tokenizer_reuse/report.md"
