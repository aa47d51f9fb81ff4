"""dvc.yaml's parameter lists follow the config: a stage reruns when, and only when, a setting it reads changes."""

import dataclasses
from pathlib import Path

import yaml

from carp.config import PolicyConfig

REPO = Path(__file__).resolve().parents[2]
# Read by decoding only (the evaluate stage), never by training.
INFERENCE_ONLY_POLICY_KEYS = {"top_k", "top_k_per_task"}


def stage_params(stage: str) -> list[str]:
    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    return stages[stage]["do"]["params"]


def test_train_policy_tracks_every_training_setting_and_not_top_k():
    tracked = {key.removeprefix("policy.") for key in stage_params("train_policy") if key.startswith("policy.")}
    training_keys = {field.name for field in dataclasses.fields(PolicyConfig)} - INFERENCE_ONLY_POLICY_KEYS
    assert "policy" not in stage_params("train_policy")
    missing, extra = training_keys - tracked, tracked - training_keys
    assert not missing and not extra, f"missing: {missing}, not training settings: {extra}"


def test_evaluate_tracks_every_decoding_setting():
    assert {f"policy.{key}" for key in INFERENCE_ONLY_POLICY_KEYS} <= set(stage_params("evaluate"))
