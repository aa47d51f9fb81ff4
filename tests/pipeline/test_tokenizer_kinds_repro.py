"""Every tokenizer kind trains through `dvc repro`, registers under its kind, reloads from the registry and
round-trips; a registered kind is reused through tokenizer.source, and one of another kind is refused in one line.
The run starts from a copy of the shared demos workspace (``lift_demos``): its demos stand."""

from pathlib import Path

import pytest
import torch
import yaml

from carp.config.tokenizer_kinds import TOKENIZER_KINDS
from carp.tokenizer.kinds.artifact import artifact_kind, load_any_artifact
from carp.tracking.registry import fetch_registered_tokenizer
from tests.pipeline.shared_workspaces import copy_pipeline
from tests.pipeline.workspace import dvc, run, stages_run

pytestmark = pytest.mark.slow

# Small fits: the kinds trained by Adam take a few dozen steps, the byte-pair encoding a small vocabulary.
TINY_KINDS = {
    "policies": ["next_token"],
    "tokenizer_fast": {"vocabulary_size": 256},
    "tokenizer_bspline": {"control_points": 6, "bins": 32},
    "tokenizer_binning": {"bins": 32},
    "tokenizer_fsq": {"levels": [5, 4], "hidden_channels": 8, "steps": 20, "batch_size": 32},
    "tokenizer_joint_msvq": {
        "scales": [1, 2],
        "codebook_size": 16,
        "latent_channels": 4,
        "hidden_channels": 8,
        "steps": 20,
        "batch_size": 32,
    },
    "tokenizer_residual_vq": {
        "num_layers": 2,
        "num_codes": 8,
        "latent_width": 8,
        "hidden_width": 16,
        "steps": 20,
        "batch_size": 32,
    },
}


def set_tokenizer(workspace: Path, **values) -> None:
    params = yaml.safe_load((workspace / "params.yaml").read_text())
    params["tokenizer"].update(values)
    (workspace / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))


def test_every_kind_trains_registers_reloads_and_round_trips(lift_demos, tmp_path):
    workspace = copy_pipeline(lift_demos, tmp_path, TINY_KINDS)
    uri = f"sqlite:///{workspace / 'mlflow.db'}"
    references = {}
    for kind in TOKENIZER_KINDS:
        set_tokenizer(workspace, kind=kind)
        done = run(dvc("repro", "register_tokenizer"), workspace)
        assert done.returncode == 0, done.stderr[-3000:]
        assert {"train_tokenizer", "register_tokenizer"} <= stages_run(done.stdout)
        reference = yaml.safe_load((workspace / "models" / "tokenizer_ref.json").read_text())
        expected = "carp-tokenizer-panda-abs10" if kind == "carp_msvq" else f"carp-tokenizer-{kind}-panda-abs10"
        assert reference["name"] == expected
        local = load_any_artifact(workspace / "models" / "tokenizer", reference["sha256"])
        fetched, _ = fetch_registered_tokenizer(uri, f"models:/{reference['name']}@default")
        assert artifact_kind(fetched) == artifact_kind(local) == kind and fetched.sha256 == local.sha256
        metrics = yaml.safe_load((workspace / "reports" / "tokenizer" / "metrics.json").read_text())
        assert metrics["rmse_percent_range/mean"] < 100.0
        if kind != "carp_msvq":
            assert metrics["invalid_rate"] == 0.0 and metrics["tokens_per_chunk/mean"] >= 1
            chunks = torch.rand(4, 16, 10) * 1.6 - 0.8
            assert torch.equal(fetched.tokenizer.encode(chunks).ids, local.tokenizer.encode(chunks).ids)
            decoded = fetched.tokenizer.decode(fetched.tokenizer.encode(chunks))
            assert decoded.actions.shape == (4, 16, 10) and decoded.invalid_count == 0
        references[kind] = f"models:/{reference['name']}@default"

    # Nothing changed: a second run reruns nothing but the always-run check.
    again = run(dvc("repro", "register_tokenizer"), workspace)
    assert stages_run(again.stdout) == {"check_inputs"}, again.stdout[-2000:]

    # A registered kind is reused: fetched, measured here, and referenced with its version's hash.
    set_tokenizer(workspace, kind="fast", source=references["fast"])
    reused = run(dvc("repro", "register_tokenizer"), workspace)
    assert reused.returncode == 0, reused.stderr[-3000:]
    reference = yaml.safe_load((workspace / "models" / "tokenizer_ref.json").read_text())
    assert load_any_artifact(workspace / "models" / "tokenizer", reference["sha256"]).kind == "fast"

    # One of another kind is refused in one line naming the registered model, the key and both values.
    set_tokenizer(workspace, kind="binning", source=references["fast"])
    refused = run(dvc("repro", "train_tokenizer"), workspace)
    assert refused.returncode != 0
    assert (
        f"error: {references['fast']}: tokenizer.kind is 'fast' in the tokenizer but the params ask for 'binning'"
        in refused.stderr.splitlines()
    ), refused.stderr[-2000:]
