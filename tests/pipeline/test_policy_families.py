"""End to end with two policy families: `dvc repro` on tiny params trains and evaluates CARP and a tiny DP-T beside it,
the report compares them, and a change to one family's params makes only that family's stage stale."""

import json
import sys

import pytest
import yaml

from tests.pipeline.workspace import make_workspace, run, stages_run

FAMILIES = {
    "policies": ["carp", "diffusion_transformer"],
    "diffusion_transformer": {"num_layers": 1, "num_heads": 2, "width": 16, "num_train_steps": 10, "warmup_steps": 2},
    "inference": {"diffusion_transformer": {"sampler": "ddim", "num_inference_steps": 2}},
}


def stale_stages(workspace) -> set[str]:
    """Stages `dvc status` reports as changed, without the always-run input check."""
    status = run([sys.executable, "-m", "dvc", "status", "--json"], workspace)
    assert status.returncode == 0, status.stderr[-3000:]
    return set(json.loads(status.stdout)) - {"check_inputs"}


@pytest.mark.slow
def test_two_families_train_evaluate_and_report_side_by_side(tmp_path):
    workspace = make_workspace(tmp_path / "carp", FAMILIES)
    first = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert first.returncode == 0, first.stderr[-3000:]
    for policy in FAMILIES["policies"]:
        for output in (
            f"models/policy/lift/{policy}/seed0/policy.pt",
            f"reports/policy/lift/{policy}/seed0/metrics.json",
            f"reports/policy/lift/{policy}/seed0/history.csv",
            f"reports/eval/lift/{policy}/seed0.json",
            f"reports/eval/lift/{policy}/seed0_episodes.csv",
        ):
            assert (workspace / output).exists(), output
    carp = json.loads((workspace / "reports/eval/lift/carp/seed0.json").read_text())
    baseline = json.loads((workspace / "reports/eval/lift/diffusion_transformer/seed0.json").read_text())
    assert (carp["policy_type"], carp["backend"], carp["inference"]) == ("carp", "onnxruntime", "greedy")
    assert (baseline["policy_type"], baseline["backend"], baseline["inference"]) == (
        "diffusion_transformer",
        "torch",
        "DDIM-2",
    )
    assert carp["model_calls_per_chunk"] == 3 and baseline["model_calls_per_chunk"] == 2
    assert baseline["episodes"] == 2 and baseline["latency_predict_ms_median"] > 0
    report = (workspace / "reports/report.md").read_text()
    table = report.split("## Policies on lift", 1)[1].split("##", 1)[0]
    assert "| carp " in table and "| diffusion_transformer " in table and "DDIM-2" in table
    assert "over 400 control steps" in report
    assert (workspace / "reports/figures/success_vs_latency.png").exists()

    second = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert second.returncode == 0, second.stderr[-3000:]
    assert stages_run(second.stdout) == {"check_inputs"}, second.stdout

    # A change to one family's section or inference settings reaches that family's stages only.
    params_file = workspace / "params.yaml"
    original = params_file.read_text()
    for change, expected in (
        (("diffusion_transformer", "learning_rate", 3e-4), {"train_policy@lift-diffusion_transformer"}),
        (("carp", "depth", 2), {"train_policy@lift-carp"}),
        (
            ("inference", "diffusion_transformer", {"sampler": "ddpm", "num_inference_steps": 4}),
            {"evaluate@lift-diffusion_transformer"},
        ),
        (("training", "epochs", 3), {"train_policy@lift-carp", "train_policy@lift-diffusion_transformer"}),
    ):
        section, key, value = change
        params = yaml.safe_load(original)
        params[section][key] = value
        params_file.write_text(yaml.safe_dump(params, sort_keys=False))
        assert stale_stages(workspace) == expected, change
    params_file.write_text(original)
