"""dvc.yaml's parameter lists follow the config: a stage reruns when, and only when, a setting it reads changes."""

import dataclasses
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from dvc.repo import Repo

from carp.config import params_from_dict
from carp.policies.registry import family_names, get_family

REPO = Path(__file__).resolve().parents[2]


def resolved_params(workspace: Path, policies: list[str], **overrides) -> dict[str, list[str]]:
    """Stage name -> the params.yaml keys DVC tracks for it, as DVC resolves dvc.yaml for `policies` (and
    top-level `overrides`)."""
    for name in ("dvc.yaml", "params.yaml"):
        shutil.copy(REPO / name, workspace / name)
    (workspace / ".dvc").mkdir(exist_ok=True)
    params = yaml.safe_load((workspace / "params.yaml").read_text())
    params["policies"] = policies
    params.update(overrides)
    (workspace / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    with Repo(str(workspace), uninitialized=True) as repo:
        return {
            stage.name: [key for dep in stage.deps if hasattr(dep, "params") for key in dep.params]
            for stage in repo.index.stages
        }


@pytest.fixture(scope="module")
def stages(tmp_path_factory) -> dict[str, list[str]]:
    return resolved_params(tmp_path_factory.mktemp("stages"), ["carp"])


def test_train_policy_tracks_its_family_section_and_the_shared_loop_but_no_inference_setting(stages):
    assert stages["train_policy@lift-carp-0"] == [
        "scales",
        "codebook_size",
        "data.obs_steps",
        "data.action_horizon",
        "data.action_steps",
        "training",
        "carp",
        "device",
        "image_encoder",
    ]


def test_evaluate_tracks_its_familys_inference_section_only(stages):
    tracked = stages["evaluate@lift-carp-0"]
    assert "inference.carp" in tracked and "eval" in tracked
    assert "carp" not in tracked and "training" not in tracked


@pytest.mark.parametrize("name", family_names())
def test_no_setting_is_both_a_training_and_an_inference_setting(name):
    family = get_family(name)
    config_keys = {field.name for field in dataclasses.fields(family.config_class)}
    inference_keys = {field.name for field in dataclasses.fields(family.inference_class)}
    assert not config_keys & inference_keys


def test_every_default_family_section_is_in_params_yaml():
    """DVC hashes `<family>` and `inference.<family>` as written in params.yaml, so each must be there."""
    raw = yaml.safe_load((REPO / "params.yaml").read_text())
    params = params_from_dict(raw)
    for name in family_names():
        assert name in raw and name in raw["inference"], name
        assert params.family_config(name) == get_family(name).config_class(**raw[name])


def test_the_default_run_has_no_multi_task_stage(stages):
    assert [name for name in stages if "multitask" in name] == []


def test_the_default_run_registers_no_policy(stages):
    assert [name for name in stages if name.startswith("register_policy")] == []


def test_registration_fans_out_over_the_registered_families_and_seeds_and_tracks_the_aliases(tmp_path):
    stages = resolved_params(tmp_path, ["carp", "next_token"], register=["next_token"], seeds=[0, 1])
    assert sorted(name for name in stages if name.startswith("register_policy")) == [
        "register_policy@lift-next_token-0",
        "register_policy@lift-next_token-1",
    ]
    # `seeds` decides which seed's version carries the plain alias.
    assert stages["register_policy@lift-next_token-1"] == ["tracking.uri", "tracking.policy_alias", "seeds"]


def test_the_registration_stage_refuses_a_family_missing_from_register_in_one_line(tmp_path):
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params.update(policies=["carp", "next_token"], register=["carp"])
    params_path = tmp_path / "params.yaml"
    params_path.write_text(yaml.safe_dump(params, sort_keys=False))
    completed = subprocess.run(
        [sys.executable, str(REPO / "pipeline" / "register_policy.py"), "--params", str(params_path)]
        + ["--task", "lift", "--policy", "next_token", "--seed", "0"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert completed.returncode == 1
    assert completed.stderr.strip().splitlines() == [
        f"error: {params_path}: register=['carp']: --policy next_token is not listed"
    ]


def test_multi_task_stages_fan_out_over_multitask_and_seeds_and_track_the_task_list(tmp_path):
    stages = resolved_params(tmp_path, ["carp"], tasks=["can", "square"], multitask=["next_token"], seeds=[0, 1])
    assert sorted(name for name in stages if "multitask" in name) == [
        "evaluate_multitask@can-next_token-0",
        "evaluate_multitask@can-next_token-1",
        "evaluate_multitask@square-next_token-0",
        "evaluate_multitask@square-next_token-1",
        "train_multitask@next_token-0",
        "train_multitask@next_token-1",
    ]
    # The task list is the policy's task ids; its family section is its model.
    assert {"tasks", "training", "next_token"} <= set(stages["train_multitask@next_token-0"])
    assert "inference.next_token" in stages["evaluate_multitask@can-next_token-0"]
    assert "multitask" in stages["report"]
    # The single-task stages are those of a run without multi-task.
    assert "train_policy@can-carp-0" in stages and "train_policy@can-next_token-0" not in stages


@pytest.mark.slow
def test_the_multi_task_stages_refuse_a_family_missing_from_multitask_in_one_line(tmp_path):
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params.update(tasks=["can", "square"], multitask=["carp"])
    params_path = tmp_path / "params.yaml"
    params_path.write_text(yaml.safe_dump(params, sort_keys=False))
    for script, task in (("train_policy.py", []), ("evaluate.py", ["--task", "can"])):
        completed = subprocess.run(
            [sys.executable, str(REPO / "pipeline" / script), "--params", str(params_path), "--multitask", *task]
            + ["--policy", "next_token", "--seed", "0"],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert completed.returncode == 1
        assert completed.stderr.strip().splitlines() == [
            f"error: {params_path}: multitask=['carp']: --policy next_token is not listed"
        ]


@pytest.mark.parametrize("script", ["train_policy.py", "evaluate.py"])
def test_a_per_family_stage_refuses_a_family_missing_from_policies_in_one_line(script, tmp_path):
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["policies"] = ["carp"]
    params_path = tmp_path / "params.yaml"
    params_path.write_text(yaml.safe_dump(params, sort_keys=False))
    completed = subprocess.run(
        [sys.executable, str(REPO / "pipeline" / script), "--params", str(params_path), "--task", "lift"]
        + ["--policy", "next_token", "--seed", "0"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert completed.returncode == 1
    assert completed.stderr.strip().splitlines() == [
        f"error: {params_path}: policies=['carp']: --policy next_token is not listed"
    ]


def test_only_ingest_tracks_the_image_settings(stages):
    image_settings = {"data.observations", "data.cameras", "data.image_size", "data.proprioception_keys"}
    assert image_settings <= set(stages["ingest@lift"])
    assert [name for name, keys in stages.items() if image_settings & set(keys) and name != "ingest@lift"] == []
    assert [name for name, keys in stages.items() if "image_encoder" in keys] == ["train_policy@lift-carp-0"]


def test_the_reports_statistics_are_no_dependency_of_the_evaluations(tmp_path):
    # The paired tests and verdicts are the report's: a change to them reruns the report, never the hours of
    # evaluation episodes. The evaluate stage imports nothing of carp.reporting, and depends on none of its files.
    for name in ("dvc.yaml", "params.yaml"):
        shutil.copy(REPO / name, tmp_path / name)
    (tmp_path / ".dvc").mkdir()
    with Repo(str(tmp_path), uninitialized=True) as repo:
        deps = {stage.name: [dep.def_path for dep in stage.deps] for stage in repo.index.stages}
    statistics = "src/carp/reporting/statistics.py"
    for stage in ("evaluate@lift-carp-0", "train_policy@lift-carp-0"):
        assert not [path for path in deps[stage] if statistics.startswith(path.rstrip("/") + "/")], deps[stage]
    assert any(statistics == path or statistics.startswith(path + "/") for path in deps["report"]), deps["report"]
    imported = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys; sys.path.insert(0, 'pipeline'); import evaluate; "
            "print(sorted(name for name in sys.modules if name.startswith('carp.reporting')))",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert imported.returncode == 0, imported.stderr[-3000:]
    assert imported.stdout.strip().splitlines()[-1] == "[]"
