"""`dvc repro` with FAST's tokens and the next-token family: it trains, evaluates with the repaired share, reloads
without the pipeline's tokenizer folder, and a second run reruns nothing. The run starts from a copy of the shared arm
pipeline, whose demos stand."""

import json
import shutil

import numpy as np
import pytest
import yaml

from carp.policies.base import count_parameters
from carp.policies.context import MsvqLayout
from carp.policies.next_token.config import NextTokenConfig
from carp.policies.next_token.kind_policy import NextTokenKindPolicy
from carp.policies.next_token.matched_size import msvq_parameters, width_nearest
from carp.policies.registry import load_policy
from tests.pipeline.shared_workspaces import copy_pipeline
from tests.pipeline.workspace import dvc, run, stages_run

pytestmark = pytest.mark.slow

PARAMS = {
    "tokenizer": {"kind": "fast"},
    "tokenizer_fast": {"vocabulary_size": 256},
    "policies": ["next_token"],
    "next_token": {"depth": 1, "width": 16, "num_heads": 2, "warmup_steps": 2},
}


def test_fast_tokens_train_and_evaluate_with_the_next_token_family(lift_pipeline, tmp_path):
    workspace = copy_pipeline(lift_pipeline, tmp_path, PARAMS)
    done = run(dvc("repro"), workspace, timeout=1800)
    assert done.returncode == 0, done.stderr[-3000:]
    assert {"train_tokenizer", "train_policy@lift-next_token-0", "evaluate@lift-next_token-0"} <= stages_run(
        done.stdout
    )
    summary = json.loads((workspace / "reports" / "eval" / "lift" / "next_token" / "seed0.json").read_text())
    assert summary["policy_type"] == "next_token" and summary["episodes"] == 2
    assert 0.0 <= summary["repaired_chunk_rate"] <= 1.0 and summary["repaired_chunks"] >= 0

    # The checkpoint decodes on its own: the pipeline's tokenizer folder is not read.
    checkpoint = workspace / "models" / "policy" / "lift" / "next_token" / "seed0" / "policy.pt"
    shutil.move(workspace / "models" / "tokenizer", tmp_path / "tokenizer")
    policy = load_policy(checkpoint)
    shutil.move(tmp_path / "tokenizer", workspace / "models" / "tokenizer")
    assert isinstance(policy, NextTokenKindPolicy) and policy.tokenizer.kind == "fast"
    # Trained at the width whose size matches the section's over carp_msvq's tokens (next_token.match_size).
    params = yaml.safe_load((workspace / "params.yaml").read_text())
    layout = MsvqLayout(tuple(params["scales"]), params["codebook_size"])
    section, transformer = NextTokenConfig(**PARAMS["next_token"]), policy.transformer
    target = msvq_parameters(section, transformer.obs_dim, 2, 10, layout)
    matched, _ = width_nearest(
        section, target, lambda config: policy.transformer_for(config, transformer.obs_dim, 2, policy.tokenizer)
    )
    assert transformer.config.width == matched.width
    assert abs(count_parameters(transformer) - target) <= 0.1 * target
    obs = np.zeros((1, 2, policy.obs_normalizer.num_features), dtype=np.float32)
    assert policy.predict_action(obs).shape == (1, 16, 10)

    again = run(dvc("repro"), workspace, timeout=600)
    assert again.returncode == 0, again.stderr[-3000:]
    assert stages_run(again.stdout) == {"check_inputs"}, again.stdout[-2000:]
