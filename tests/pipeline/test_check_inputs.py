"""The always-run check_inputs stage: params typos fail even when nothing is stale, and a user's demo file is a
tracked dependency of collect (replaced in place, it reruns collect; touched, it reruns nothing)."""

import json
import sys

import pytest
import yaml

from tests.conftest import write_synthetic_file
from tests.pipeline.workspace import REPO, make_workspace, run, stages_run

USER_FILE = "own/lift.hdf5"


def repro(workspace, *targets):
    """`dvc repro` of `targets`, or with "--dry" first, what `make dry` shows for them."""
    if targets and targets[0] == "--dry":
        return run([sys.executable, str(REPO / "tools" / "dvc_dry.py"), "repro", *targets[1:]], workspace)
    return run([sys.executable, "-m", "dvc", "repro", *targets], workspace)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    directory = tmp_path_factory.mktemp("check_inputs") / "carp"
    directory.mkdir()
    write_synthetic_file(directory / USER_FILE, lengths=(30, 25, 40, 20))
    workspace = make_workspace(directory, {"data": {"raw_files": {"lift": USER_FILE}}})
    first = repro(workspace, "ingest@lift")
    assert first.returncode == 0, first.stderr[-3000:]
    assert stages_run(first.stdout) == {"check_inputs", "collect@lift", "ingest@lift"}
    return workspace


def processed_steps(workspace) -> int:
    return json.loads((workspace / "data/processed/lift/summary.json").read_text())["steps"]


@pytest.mark.slow
def test_user_file_replaced_in_place_reruns_collect_and_touched_does_not(workspace):
    assert processed_steps(workspace) == 30 + 25 + 40 + 20
    (workspace / USER_FILE).touch()
    unchanged = repro(workspace, "ingest@lift")
    assert unchanged.returncode == 0, unchanged.stderr[-3000:]
    assert stages_run(unchanged.stdout) == {"check_inputs"}, unchanged.stdout + unchanged.stderr[-3000:]

    write_synthetic_file(workspace / USER_FILE, lengths=(35, 30, 45), seed=1)
    replaced = repro(workspace, "ingest@lift")
    assert replaced.returncode == 0, replaced.stderr[-3000:]
    assert stages_run(replaced.stdout) == {"check_inputs", "collect@lift", "ingest@lift"}
    assert processed_steps(workspace) == 35 + 30 + 45


@pytest.mark.slow
@pytest.mark.parametrize("section, key", [(None, "foo"), ("carp", "epoch"), ("data", "num_demo")])
def test_params_typo_fails_the_pipeline_even_when_nothing_is_stale(workspace, section, key):
    params_file = workspace / "params.yaml"
    original = params_file.read_text()
    params = yaml.safe_load(original)
    (params[section] if section else params)[key] = 3
    dotted = f"{section}.{key}" if section else key
    try:
        params_file.write_text(yaml.safe_dump(params, sort_keys=False))
        result = repro(workspace, "ingest@lift")
        assert result.returncode != 0
        errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
        assert len(errors) == 1 and f"{dotted}: unknown key" in errors[0], result.stderr[-2000:]
        assert "Traceback" not in result.stderr
        assert stages_run(result.stdout) == {"check_inputs"}
    finally:
        params_file.write_text(original)
    # The refused file left the last records in place, so with the typo fixed a dry run lists only the input check.
    dry = repro(workspace, "--dry", "ingest@lift")
    assert dry.returncode == 0, dry.stderr[-3000:]
    assert stages_run(dry.stdout) == {"check_inputs"}, dry.stdout


@pytest.mark.slow
def test_exp_run_with_an_added_unknown_key_fails(workspace):
    result = run([sys.executable, "-m", "dvc", "exp", "run", "-S", "+carp.epoch=3"], workspace)
    assert result.returncode != 0
    assert "carp.epoch: unknown key" in result.stderr
    run(["git", "checkout", "params.yaml"], workspace)


@pytest.mark.slow
def test_dry_run_after_a_run_lists_a_new_tasks_stages_and_not_the_built_ones(workspace):
    params_file = workspace / "params.yaml"
    original = params_file.read_text()
    params = yaml.safe_load(original)
    params["tasks"] = ["lift", "can"]
    try:
        params_file.write_text(yaml.safe_dump(params, sort_keys=False))
        dry = repro(workspace, "--dry", "ingest@lift", "ingest@can")
        assert dry.returncode == 0, dry.stderr[-3000:]
        assert stages_run(dry.stdout) == {"check_inputs", "collect@can", "ingest@can"}, dry.stdout
        assert not (workspace / "data/raw/can.hdf5").exists()
    finally:
        params_file.write_text(original)
