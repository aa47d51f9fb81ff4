"""End to end with a multi-task policy: `dvc repro` on tiny params over Lift and Can (a 10-wide and a 14-wide `object`
observation, padded inside the policy) trains the single-task CARPs and one multi-task CARP over both tasks,
evaluates it on each task beside them, and the report sets them side by side; a second run runs nothing but the
input check. A run of the multi-task policy alone, referencing the single-task evaluations, reruns only the report.
The run starts from a copy of the shared arm pipeline, whose Lift demos stand."""

import json
import shutil
import sys

import pytest
import yaml

from carp.policies.registry import load_policy
from carp.serving.startup import load_served_model
from tests.pipeline.shared_workspaces import copy_pipeline
from tests.pipeline.workspace import run, stages_run

TASKS = ["lift", "can"]
MULTITASK = {
    "tasks": TASKS,
    "policies": ["carp"],
    "multitask": ["carp"],
    "data": {"num_demos": 2},
    "eval": {"episodes": 1, "workers": 1},
}


@pytest.mark.slow
def test_a_multi_task_policy_trains_over_every_task_and_is_evaluated_on_each(lift_pipeline, tmp_path):
    workspace = copy_pipeline(lift_pipeline, tmp_path, MULTITASK)
    first = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert first.returncode == 0, first.stderr[-3000:]
    assert {"train_multitask@carp-0", "evaluate_multitask@lift-carp-0", "evaluate_multitask@can-carp-0"} <= (
        stages_run(first.stdout)
    )
    for output in (
        "models/policy/multitask/carp/seed0/policy.pt",
        "reports/policy/multitask/carp/seed0/history.csv",
        "reports/policy/multitask/carp/seed0/metrics.json",
        *(f"models/policy/{task}/carp/seed0/policy.pt" for task in TASKS),
        *(f"reports/eval/{task}/carp/seed0.json" for task in TASKS),
        *(
            f"reports/eval/{task}/carp-multitask/seed0{suffix}"
            for task in TASKS
            for suffix in (".json", "_episodes.csv")
        ),
        "reports/report.md",
    ):
        assert (workspace / output).exists(), output
    # One checkpoint knows both tasks, in the order of `tasks`.
    policy = load_policy(workspace / "models/policy/multitask/carp/seed0/policy.pt")
    assert list(policy.tasks.names) == TASKS
    # It records its serving protocol: `carp serve --task` serves either task from the file alone.
    # Each task's own observation widths: `object` is 10 wide in Lift, 14 in Can (the policy pads Lift's).
    object_widths = {}
    for task in TASKS:
        served, spec = load_served_model(workspace / "models/policy/multitask/carp/seed0/policy.pt", task=task)
        assert served.policy.tasks.selected == task and spec.obs_widths is not None
        object_widths[task] = spec.obs_widths[spec.obs_keys.index("object")]
    assert object_widths == {"lift": 10, "can": 14}
    assert policy.obs_normalizer.num_features == sum(policy.tasks.obs_widths["can"])
    # The shared tokenizer's error on each task's own held-out windows.
    tokenizer_metrics = json.loads((workspace / "reports/tokenizer/metrics.json").read_text())
    assert all(f"task/{task}/rmse_percent_range/mean" in tokenizer_metrics for task in TASKS)
    metrics = json.loads((workspace / "reports/policy/multitask/carp/seed0/metrics.json").read_text())
    assert "final_loss" in metrics
    for task in TASKS:
        summary = json.loads((workspace / f"reports/eval/{task}/carp-multitask/seed0.json").read_text())
        assert summary["episodes"] == 1 and summary["policy_type"] == "carp"
    report = (workspace / "reports/report.md").read_text()
    section = report.split("## Multi-task", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith(("| lift ", "| can ")) and "| carp " in line]
    assert len(rows) == 2 and all("/1 (" in row for row in rows)
    pairs = [line for line in section.splitlines() if "| carp-multitask vs carp " in line]
    assert [pair.split("|")[1].strip() for pair in pairs] == TASKS

    second = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert second.returncode == 0, second.stderr[-3000:]
    assert stages_run(second.stdout) == {"check_inputs"}

    # The single-task evaluations kept apart, a run of the multi-task policy alone (`policies: []`) referencing them:
    # nothing trains again, and the report still pairs the multi-task policy with each single-task one.
    for task in TASKS:
        shutil.copytree(workspace / f"reports/eval/{task}/carp", workspace / f"earlier/eval/{task}/carp")
    params_file = workspace / "params.yaml"
    params = yaml.safe_load(params_file.read_text())
    params["policies"] = []
    params["comparison"]["references"] = ["earlier/eval"]
    params_file.write_text(yaml.safe_dump(params, sort_keys=False))
    alone = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert alone.returncode == 0, alone.stderr[-3000:]
    assert stages_run(alone.stdout) == {"check_inputs", "report"}
    report = (workspace / "reports/report.md").read_text()
    section = report.split("## Multi-task", 1)[1].split("\n## ", 1)[0]
    pairs = [line for line in section.splitlines() if "carp-multitask vs carp" in line and line.startswith("| ")]
    assert [pair.split("|")[1].strip() for pair in pairs] == TASKS
    assert all(f"{task}, " in section for task in TASKS) and "carp (training seeds 0) from earlier/eval" in report
