"""`dvc repro --dry`, `dvc exp run --dry` and `dvc status` answer on a fresh clone, before any stage has run."""

import os
import re
import shutil
import subprocess
import sys

import pytest

from carp.dvc_dry_run import patch_stage_cache
from tests.pipeline.workspace import REPO, make_workspace, run

DVC = [sys.executable, "-m", "dvc"]


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
    dry = run([*DVC, "repro", "--dry"], tmp_path)
    assert dry.returncode == 0, dry.stderr[-2000:]
    assert _would_run(dry.stdout) == ["produce", "consume"]
    assert not (tmp_path / "made.txt").exists()
    # A real run is untouched by the fix: it runs both stages and a second one finds them cached.
    assert run([*DVC, "repro"], tmp_path).returncode == 0
    assert (tmp_path / "used.txt").read_text() == "made\n"
    assert _would_run(run([*DVC, "repro", "--dry"], tmp_path).stdout) == []


def test_the_patch_is_applied_once_and_only_to_dry_runs():
    import dvc.stage.cache as stage_cache

    # The project's Python installs it at start-up (tools/carp-dvc-dry-run.pth, `make setup`).
    assert getattr(stage_cache.StageCache.restore, "carp_dry_run_patch", False)
    patched = stage_cache.StageCache.restore
    patch_stage_cache(stage_cache)
    assert stage_cache.StageCache.restore is patched


def test_the_startup_hook_applies_the_fix_only_where_the_checkout_has_it(tmp_path):
    # One venv can serve several checkouts (PYTHONPATH, an older commit): the hook must not fail Python in those.
    site_dir = tmp_path / "site-packages"
    site_dir.mkdir()
    shutil.copy(REPO / "tools/carp-dvc-dry-run.pth", site_dir)
    older = tmp_path / "older"
    (older / "carp").mkdir(parents=True)
    (older / "carp/__init__.py").write_text("")
    probe = (
        "import site, sys; site.addsitedir(sys.argv[1]); "
        "print(any(type(finder).__name__ == '_PatchAfterImport' for finder in sys.meta_path))"
    )
    for source, installed in ((REPO / "src", "True"), (older, "False")):
        started = subprocess.run(
            [sys.executable, "-S", "-c", probe, str(site_dir)],
            env={**os.environ, "PYTHONPATH": str(source)},
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert started.returncode == 0 and started.stderr == "", started.stderr
        assert started.stdout.strip() == installed, source


@pytest.mark.slow
def test_a_fresh_clone_answers_dry_runs_and_status_with_every_seed_fanned_out(tmp_path):
    workspace = make_workspace(tmp_path / "carp", {"seeds": [0, 1], "policies": ["carp", "next_token"]})
    dry = run([*DVC, "repro", "--dry"], workspace)
    assert dry.returncode == 0, dry.stderr[-2000:]
    stages = _would_run(dry.stdout)
    assert stages[:2] == ["check_inputs", "collect@lift"]
    for family in ("carp", "next_token"):
        for seed in (0, 1):
            assert f"train_policy@lift-{family}-{seed}" in stages and f"evaluate@lift-{family}-{seed}" in stages
    assert stages[-1] == "report"
    assert [stage for stage in stages if stage.startswith("register_policy")] == []  # register: [] by default
    assert not (workspace / "data").exists(), "a dry run runs nothing"
    experiment = run([*DVC, "exp", "run", "--dry", "-S", "tasks=[lift,can]"], workspace)
    assert experiment.returncode == 0, experiment.stderr[-2000:]
    assert "collect@can" in _would_run(experiment.stdout)
    status = run([*DVC, "status"], workspace)
    assert status.returncode == 0 and "collect@lift" in status.stdout
