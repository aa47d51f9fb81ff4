"""`make dry` (`tools/dvc_dry.py`) answers on a fresh clone, before any stage has run, and installs nothing."""

import os
import re
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from tests.pipeline.workspace import REPO, make_workspace, run

DVC = [sys.executable, "-m", "dvc"]
DRY = [sys.executable, str(REPO / "tools" / "dvc_dry.py")]


def _would_run(stdout: str) -> list[str]:
    return re.findall(r"Running stage '([^']+)'", stdout)


def test_a_dry_run_lists_stages_whose_inputs_an_upstream_stage_has_not_made_yet(tmp_path):
    for command in (
        ["git", "init", "-q"],
        [*DVC, "init", "-q"],
        [*DVC, "stage", "add", "-q", "-n", "produce", "-o", "made.txt", "echo made > made.txt"],
        [*DVC, "stage", "add", "-q", "-n", "consume", "-d", "made.txt", "-o", "used.txt", "cp made.txt used.txt"],
    ):
        assert run(command, tmp_path).returncode == 0, command
    dry = run([*DRY, "repro"], tmp_path)
    assert dry.returncode == 0, dry.stderr[-2000:]
    assert _would_run(dry.stdout) == ["produce", "consume"]
    assert not (tmp_path / "made.txt").exists()
    # DVC's own dry run, in its own process, is not patched: it still stops where issue 9818 says.
    plain = run([*DVC, "repro", "--dry"], tmp_path)
    assert plain.returncode != 0 or _would_run(plain.stdout) != ["produce", "consume"]
    # Real runs are untouched: both stages run, and a dry run after them finds them cached.
    assert run([*DVC, "repro"], tmp_path).returncode == 0
    assert (tmp_path / "used.txt").read_text() == "made\n"
    assert _would_run(run([*DRY, "repro"], tmp_path).stdout) == []


def test_the_dry_tool_runs_only_dry_commands():
    refused = subprocess.run([*DRY, "push"], capture_output=True, text=True, timeout=60)
    assert refused.returncode != 0
    assert refused.stderr.strip().splitlines()[-1].startswith("error: tools/dvc_dry.py: push: must start with")


def test_nothing_patches_dvc_at_interpreter_start():
    site = Path(sysconfig.get_paths()["purelib"])
    assert not list(site.glob("*dry-run*.pth")), "no start-up hook in the venv"
    probe = "import dvc.stage.cache as c; print(getattr(c.StageCache.restore, 'carp_dry_run_patch', False))"
    started = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, env=os.environ)
    assert started.stdout.strip() == "False", started.stderr


@pytest.mark.slow
def test_a_fresh_clone_answers_dry_runs_and_status_with_every_seed_fanned_out(tmp_path):
    workspace = make_workspace(tmp_path / "carp", {"seeds": [0, 1], "policies": ["carp", "next_token"]})
    dry = run([*DRY, "repro"], workspace)
    assert dry.returncode == 0, dry.stderr[-2000:]
    stages = _would_run(dry.stdout)
    assert stages[:2] == ["check_inputs", "collect@lift"]
    for family in ("carp", "next_token"):
        for seed in (0, 1):
            assert f"train_policy@lift-{family}-{seed}" in stages and f"evaluate@lift-{family}-{seed}" in stages
    assert stages[-1] == "report"
    assert [stage for stage in stages if stage.startswith("register_policy")] == []  # register: [] by default
    assert not (workspace / "data").exists(), "a dry run runs nothing"
    experiment = run([*DRY, "exp", "run", "-S", "tasks=[lift,can]"], workspace)
    assert experiment.returncode == 0, experiment.stderr[-2000:]
    assert "collect@can" in _would_run(experiment.stdout)
    status = run([*DVC, "status"], workspace)
    assert status.returncode == 0 and "collect@lift" in status.stdout
