"""End to end: the consistency_policy stage trains its edm_unet teacher, and reuses it when only the student changes.

The student's train_policy stage writes `teacher.pt` beside `policy.pt`; the teacher's training state stays in the
stage's checkpoints, so a rerun for a student-only change distils again from the same teacher without retraining it.
The teacher's params reach the student's stage alone (through check_inputs' `data/inputs/teachers/<family>.json`).
The test starts from a copy of the shared arm pipeline: its demos and tokenizer stand, the policies' stages run.
"""

import json
import sys

import pytest
import yaml

from tests.pipeline.shared_workspaces import TINY_UNET, copy_pipeline
from tests.pipeline.workspace import run, stages_run

STUDENT_STAGE = "train_policy@lift-consistency_policy-0"


def status(workspace) -> set[str]:
    """Stale stages after check_inputs ran (it writes the teachers' params files the training stages read)."""
    checked = run([sys.executable, "-m", "dvc", "repro", "--single-item", "check_inputs"], workspace)
    assert checked.returncode == 0, checked.stderr[-3000:]
    completed = run([sys.executable, "-m", "dvc", "status", "--json"], workspace)
    assert completed.returncode == 0, completed.stderr[-3000:]
    return set(json.loads(completed.stdout)) - {"check_inputs"}


def edit_params(workspace, change) -> None:
    params_file = workspace / "params.yaml"
    params = yaml.safe_load(params_file.read_text())
    change(params)
    params_file.write_text(yaml.safe_dump(params, sort_keys=False))


@pytest.mark.slow
def test_the_student_stage_trains_its_teacher_once_and_reuses_it(lift_pipeline, tmp_path):
    workspace = copy_pipeline(
        lift_pipeline,
        tmp_path,
        {
            "policies": ["carp", "consistency_policy"],
            "training": {"epochs": 1},
            "edm_unet": TINY_UNET,
            "consistency_policy": TINY_UNET | {"num_levels": 10},
            "eval": {"episodes": 1, "workers": 1, "max_steps": {"lift": 20}},
        },
    )
    first = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert first.returncode == 0, first.stderr[-3000:]
    seed_dir = workspace / "models/policy/lift/consistency_policy/seed0"
    assert (seed_dir / "policy.pt").is_file() and (seed_dir / "teacher.pt").is_file()
    assert "trained the edm_unet teacher of consistency_policy" in first.stdout + first.stderr
    report = json.loads((workspace / "reports/eval/lift/consistency_policy/seed0.json").read_text())
    assert (report["policy_type"], report["episodes"], report["model_calls_per_chunk"]) == ("consistency_policy", 1, 1)
    teacher_bytes, student_bytes = (seed_dir / "teacher.pt").read_bytes(), (seed_dir / "policy.pt").read_bytes()

    # The teacher's params make the student's training stale, and no other family's.
    original = (workspace / "params.yaml").read_text()
    edit_params(workspace, lambda params: params["edm_unet"].update(learning_rate=2e-4))
    assert status(workspace) == {STUDENT_STAGE}
    (workspace / "params.yaml").write_text(original)

    # A student-only change reruns the student's stage, which distils again from the same teacher.
    edit_params(workspace, lambda params: params["consistency_policy"].update(learning_rate=2e-4))
    assert status(workspace) == {STUDENT_STAGE}
    second = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert second.returncode == 0, second.stderr[-3000:]
    ran = stages_run(second.stdout)
    assert STUDENT_STAGE in ran and not any(stage.startswith("train_policy@lift-carp") for stage in ran), ran
    assert "reused the trained edm_unet teacher of consistency_policy" in second.stdout + second.stderr
    assert (seed_dir / "teacher.pt").read_bytes() == teacher_bytes
    assert (seed_dir / "policy.pt").read_bytes() != student_bytes
