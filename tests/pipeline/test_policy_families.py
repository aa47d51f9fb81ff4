"""End to end with two policy families and two training seeds: `dvc repro` on tiny params trains and evaluates CARP and
a tiny DP-T beside it, selects each seed's checkpoint on validation seeds, registers CARP's confirmed checkpoints, the
report compares them, and a change to one family's params makes only that family's stages stale. The run starts from a
copy of the shared arm pipeline: its demos and tokenizer stand, the policies' stages run."""

import json
import shutil
import sys

import pandas as pd
import pytest
import yaml

from carp.data.sources import file_sha256
from carp.tracking.registry import resolve_alias
from tests.pipeline.shared_workspaces import copy_pipeline
from tests.pipeline.workspace import run, stages_run

FAMILIES = {
    "policies": ["carp", "diffusion_transformer"],
    "register": ["carp"],
    "seeds": [0, 1],
    "training": {"snapshot_every": 1},
    "eval": {"selection": "best_validation", "validation_episodes": 2},
    "diffusion_transformer": {"num_layers": 1, "num_heads": 2, "width": 16, "num_train_steps": 10, "warmup_steps": 2},
    "inference": {"diffusion_transformer": {"sampler": "ddim", "num_inference_steps": 2}},
}


def stale_stages(workspace) -> set[str]:
    """Stages `dvc status` reports as changed, without the always-run input check."""
    status = run([sys.executable, "-m", "dvc", "status", "--json"], workspace)
    assert status.returncode == 0, status.stderr[-3000:]
    return set(json.loads(status.stdout)) - {"check_inputs"}


@pytest.mark.slow
def test_two_families_train_evaluate_and_report_side_by_side(lift_pipeline, tmp_path):
    workspace = copy_pipeline(lift_pipeline, tmp_path, FAMILIES)
    first = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert first.returncode == 0, first.stderr[-3000:]
    for policy in FAMILIES["policies"]:
        for seed in FAMILIES["seeds"]:
            for output in (
                f"models/policy/lift/{policy}/seed{seed}/policy.pt",
                f"models/policy/lift/{policy}/seed{seed}/snapshots/epoch0001.pt",
                f"reports/policy/lift/{policy}/seed{seed}/metrics.json",
                f"reports/policy/lift/{policy}/seed{seed}/history.csv",
                f"reports/eval/lift/{policy}/seed{seed}.json",
                f"reports/eval/lift/{policy}/seed{seed}_episodes.csv",
            ):
                assert (workspace / output).exists(), output
            # Both candidates ran on the validation seeds only; the chosen one then on the test seeds.
            validation = pd.read_csv(workspace / f"reports/eval/lift/{policy}/seed{seed}_validation.csv")
            assert sorted(validation["epoch"].unique()) == [1, 2]
            assert set(validation["seed"]) == {200_000, 200_001}
            episodes = pd.read_csv(workspace / f"reports/eval/lift/{policy}/seed{seed}_episodes.csv")
            assert set(episodes["seed"]) == {100_000, 100_001}
    # The two seeds trained different policies.
    weights = [(workspace / f"models/policy/lift/carp/seed{seed}/policy.pt").read_bytes() for seed in (0, 1)]
    assert weights[0] != weights[1]
    carp = json.loads((workspace / "reports/eval/lift/carp/seed0.json").read_text())
    assert carp["candidates"] == 2 and carp["selected_epoch"] in (1, 2) and carp["training_seed"] == 0
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
    comparison = report.split("## Comparison on lift", 1)[1].split("\n## ", 1)[0]
    seed_rows = [line for line in comparison.splitlines() if line.startswith("| carp ") and "| epoch " in line]
    assert len(seed_rows) == len(FAMILIES["seeds"])
    # Two training seeds are fewer than a family verdict needs: the pair's figures describe the networks only.
    assert "not decided (2 training seeds): " in comparison
    assert "compare the trained networks, not the families" in comparison
    assert "## The paper's claims on this run" in report and "CARP is faster per chunk than DP-T" in report
    assert (workspace / "reports/figures/steps_to_success_lift.png").exists()
    assert (workspace / "reports/figures/success_vs_latency.png").exists()

    # CARP's confirmed checkpoints are registered, one version per seed; DP-T, not in `register`, is not.
    uri = f"sqlite:///{workspace / 'mlflow.db'}"
    references = {}
    for seed in FAMILIES["seeds"]:
        reference = json.loads((workspace / f"models/policy_ref/lift/carp/seed{seed}.json").read_text())
        selected = json.loads((workspace / f"reports/eval/lift/carp/seed{seed}.json").read_text())["selected_epoch"]
        run_dir = workspace / f"models/policy/lift/carp/seed{seed}"
        confirmed = run_dir / ("policy.pt" if selected == 2 else f"snapshots/epoch{selected:04d}.pt")
        assert (reference["name"], reference["alias"]) == ("carp-policy-lift-carp", f"candidate-seed{seed}")
        assert reference["sha256"] == file_sha256(confirmed), seed
        references[seed] = reference
    assert references[0]["version"] != references[1]["version"]
    assert resolve_alias(uri, "models:/carp-policy-lift-carp@candidate").version == references[0]["version"]
    assert not (workspace / "models/policy_ref/lift/diffusion_transformer").exists()

    # A duel extends the two evaluated policies' test episodes in rounds: the evaluated seeds count, new ones run.
    duel = [
        sys.executable,
        "pipeline/duel.py",
        "--task",
        "lift",
        "--first",
        "carp",
        "--second",
        "diffusion_transformer",
    ]
    dueled = run([*duel, "--seed", "1", "--episodes", "4", "--round-episodes", "1", "--duels", "2"], workspace)
    assert dueled.returncode == 0, dueled.stderr[-3000:]
    assert "lift: not decided in 4 episodes" in dueled.stdout
    assert "two trained networks, not the families; alpha 0.05 split over 2 duel(s)" in dueled.stdout
    duel_dir = workspace / "reports/duel/lift/carp_vs_diffusion_transformer/seed1"
    verdict = json.loads((duel_dir / "verdict.json").read_text())
    assert (verdict["episodes"], verdict["rounds"], verdict["verdict"]) == (4, 3, "not decided")
    assert (verdict["first"], verdict["alpha"], verdict["duels"]) == ("carp (training seed 1)", 0.025, 2)
    for policy in FAMILIES["policies"]:
        duel_episodes = pd.read_csv(duel_dir / f"{policy}_episodes.csv")
        evaluated = pd.read_csv(workspace / f"reports/eval/lift/{policy}/seed1_episodes.csv")
        assert duel_episodes["seed"].tolist() == [100_000, 100_001, 100_002, 100_003]
        assert duel_episodes.head(2)["success"].tolist() == evaluated["success"].tolist()
    assert verdict["first_successes"] == pd.read_csv(duel_dir / "carp_episodes.csv")["success"].sum()
    # Run again, it resumes finished: nothing new runs and the verdict stands.
    again = run([*duel, "--seed", "1", "--episodes", "4", "--duels", "2"], workspace)
    resumed = json.loads((duel_dir / "verdict.json").read_text())
    assert again.returncode == 0 and resumed == verdict | {"rounds": 1}  # the kept episodes count as one round
    assert len(pd.read_csv(duel_dir / "carp_episodes.csv")) == 4
    # A test range extended into the collection seeds is refused before anything runs.
    shifted = yaml.safe_load((workspace / "params.yaml").read_text())
    shifted["data"]["collection_seed"] = 100_010
    (workspace / "shifted-params.yaml").write_text(yaml.safe_dump(shifted))
    overlapping = run([*duel, "--params", "shifted-params.yaml", "--seed", "1", "--episodes", "20"], workspace)
    last_line = overlapping.stderr.strip().splitlines()[-1]
    assert overlapping.returncode == 1 and last_line.startswith("error: ") and "collection seeds" in last_line
    refused = run([*duel[:-1], "next_token"], workspace)
    assert refused.returncode == 1
    assert (
        refused.stderr.strip().splitlines()[-1].startswith("error: ") and "next_token is not listed" in refused.stderr
    )

    second = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert second.returncode == 0, second.stderr[-3000:]
    assert stages_run(second.stdout) == {"check_inputs"}, second.stdout

    # A change to one family's section or inference settings reaches that family's stages only.
    params_file = workspace / "params.yaml"
    original = params_file.read_text()
    for change, expected in (
        (
            ("diffusion_transformer", "learning_rate", 3e-4),
            {"train_policy@lift-diffusion_transformer-0", "train_policy@lift-diffusion_transformer-1"},
        ),
        (("carp", "depth", 2), {"train_policy@lift-carp-0", "train_policy@lift-carp-1"}),
        (
            ("inference", "diffusion_transformer", {"sampler": "ddpm", "num_inference_steps": 4}),
            {"evaluate@lift-diffusion_transformer-0", "evaluate@lift-diffusion_transformer-1"},
        ),
        (("training", "epochs", 3), {f"train_policy@lift-{p}-{s}" for p in FAMILIES["policies"] for s in (0, 1)}),
        (("eval", "episodes", 3), {f"evaluate@lift-{p}-{s}" for p in FAMILIES["policies"] for s in (0, 1)}),
    ):
        section, key, value = change
        params = yaml.safe_load(original)
        params[section][key] = value
        params_file.write_text(yaml.safe_dump(params, sort_keys=False))
        assert stale_stages(workspace) == expected, change
    # Another training seed adds its own stages and leaves the others' alone.
    params = yaml.safe_load(original)
    params["seeds"] = [0, 1, 2]
    params_file.write_text(yaml.safe_dump(params, sort_keys=False))
    added = {f"{stage}@lift-{p}-2" for stage in ("train_policy", "evaluate") for p in FAMILIES["policies"]}
    # Registration tracks the seed list (the plain alias goes to the first seed), so every seed's registration reruns.
    registered = {f"register_policy@lift-carp-{seed}" for seed in (0, 1, 2)}
    assert stale_stages(workspace) == added | registered | {"report"}
    params_file.write_text(original)

    # Seed 1's evaluations kept apart and referenced: a run of seed 0 alone compares both seeds, as the full run did.
    whole = (workspace / "reports/report.md").read_text()
    for policy in FAMILIES["policies"]:
        kept = workspace / "earlier/eval/lift" / policy
        kept.mkdir(parents=True)
        for name in ("seed1.json", "seed1_episodes.csv"):
            shutil.copy(workspace / f"reports/eval/lift/{policy}/{name}", kept / name)
    params = yaml.safe_load(original)
    params["seeds"] = [0]
    params["comparison"]["references"] = ["earlier/eval"]
    params_file.write_text(yaml.safe_dump(params, sort_keys=False))
    referencing = run([sys.executable, "-m", "dvc", "repro"], workspace)
    assert referencing.returncode == 0, referencing.stderr[-3000:]
    assert "train_policy@lift-carp-0" not in stages_run(referencing.stdout) and "report" in stages_run(
        referencing.stdout
    )
    merged = (workspace / "reports/report.md").read_text()
    assert "carp (training seeds 1) from earlier/eval" in merged

    def comparison(report: str) -> str:
        return report.split("## Comparison on lift", 1)[1].split("\n## ", 1)[0]

    assert comparison(merged) == comparison(whole)
    # A seed of a family that the run has itself is refused, naming the file of params, the reference and the seed.
    params["comparison"]["references"] = ["reports/eval"]
    params_file.write_text(yaml.safe_dump(params, sort_keys=False))
    clash = run([sys.executable, "pipeline/report.py"], workspace)
    assert clash.returncode == 1
    assert (
        clash.stderr.strip().splitlines()[-1].startswith("error: ")
        and "training seed 0 is already in the report" in clash.stderr
    )
