"""A damaged or mismatched model file stops its stage with one `error:` line, exit 1 and nothing written.

The stages are run as the pipeline runs them (`python pipeline/<stage>.py`) in a copy of the repository that holds
only the files each check needs: both stages read their model file before anything else.
"""

import json
import shutil
import sys
from pathlib import Path

import pytest
import torch

from carp.tracking.registry import TokenizerReference
from tests.pipeline.workspace import make_workspace, run
from tests.policies.carp.factories import tiny_artifact, tiny_policy, tiny_tokenizer


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    return make_workspace(tmp_path_factory.mktemp("checkpoint-errors") / "carp")


def _stage(workspace: Path, script: str, *arguments: str):
    return run([sys.executable, f"pipeline/{script}", *arguments], workspace, timeout=300)


def _assert_refused(completed, expected: str) -> None:
    assert completed.returncode == 1, completed.stderr[-3000:]
    lines = completed.stderr.strip().splitlines()
    assert lines[-1].startswith("error: ") and expected in lines[-1], completed.stderr[-3000:]
    assert "Traceback" not in completed.stderr, completed.stderr[-3000:]


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _with_other_tokenizer(checkpoint: dict) -> None:
    checkpoint["tokenizer"] = tiny_artifact(tiny_tokenizer(seed=1)).to_payload()


def _with_other_codebook_size(checkpoint: dict) -> None:
    checkpoint["tokenizer"]["spec"]["codebook_size"] = 16


@pytest.mark.slow
@pytest.mark.parametrize(
    ("damage", "expected"),
    [
        (_truncate, "policy.pt: not a readable checkpoint, truncated or corrupt ("),
        (_with_other_tokenizer, "policy.pt: tokenizer weights have sha256 "),
        (_with_other_codebook_size, "policy.pt: policy spec does not match the tokenizer spec (codebook_size: policy"),
    ],
    ids=["truncated", "another tokenizer of the same shape", "another codebook size"],
)
def test_evaluate_refuses_a_damaged_policy(workspace, damage, expected):
    path = workspace / "models/policy/lift/carp/seed0/policy.pt"
    path.parent.mkdir(parents=True, exist_ok=True)
    if damage is _truncate:
        tiny_policy().save(path)
        _truncate(path)
    else:
        checkpoint = tiny_policy().to_checkpoint()
        damage(checkpoint)
        torch.save(checkpoint, path)
    completed = _stage(workspace, "evaluate.py", "--task", "lift", "--policy", "carp", "--seed", "0")
    _assert_refused(completed, expected)
    if damage is _with_other_tokenizer:
        recorded = tiny_policy().tokenizer_artifact.sha256
        assert f"not the sha256 {recorded[:12]}... recorded in the policy" in completed.stderr
    assert not (workspace / "reports/eval").exists()
    assert not (workspace / "mlflow.db").exists()


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["truncated", "other sha256"])
def test_train_policy_refuses_a_damaged_or_unreferenced_tokenizer(workspace, damage):
    artifact = tiny_artifact(tiny_tokenizer())
    directory = workspace / "models/tokenizer"
    directory.mkdir(parents=True, exist_ok=True)
    torch.save(artifact.to_payload(), directory / "tokenizer.pt")
    recorded = "0" * 64 if damage == "other sha256" else artifact.sha256
    reference = TokenizerReference("carp-tokenizer-test", "1", "default", "run", recorded)
    reference.save(workspace / "models/tokenizer_ref.json")
    shutil.rmtree(workspace / "models/policy", ignore_errors=True)  # the evaluate checks' files
    if damage == "truncated":
        _truncate(directory / "tokenizer.pt")
        expected = "models/tokenizer/tokenizer.pt: not a readable checkpoint, truncated or corrupt ("
    else:
        expected = (
            f"models/tokenizer/tokenizer.pt: tokenizer weights have sha256 {artifact.sha256[:12]}..., not the sha256 "
            f"000000000000... recorded in {workspace / 'models/tokenizer_ref.json'}"
        )
    completed = _stage(workspace, "train_policy.py", "--task", "lift", "--policy", "carp", "--seed", "0")
    _assert_refused(completed, expected)
    assert json.loads((workspace / "models/tokenizer_ref.json").read_text())["sha256"] == recorded
    assert not (workspace / "models/policy").exists() and not (workspace / "reports/policy").exists()
    assert not (workspace / "mlflow.db").exists()
