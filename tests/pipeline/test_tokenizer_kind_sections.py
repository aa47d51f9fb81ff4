"""Each tokenizer kind's settings are their own params section, and train_tokenizer tracks the selected kind's only."""

import shutil
from pathlib import Path

import pytest
import yaml
from dvc.repo import Repo

from carp.config import params_from_dict
from carp.config.checks import ConfigError
from carp.config.tokenizer_kinds import TOKENIZER_KINDS, kind_section

REPO = Path(__file__).resolve().parents[2]


def tracked_params(workspace: Path, **overrides) -> dict[str, list[str]]:
    """Stage name -> the params.yaml keys DVC tracks for it, with top-level `overrides` merged into params.yaml."""
    for name in ("dvc.yaml", "params.yaml"):
        shutil.copy(REPO / name, workspace / name)
    (workspace / ".dvc").mkdir(exist_ok=True)
    params = yaml.safe_load((workspace / "params.yaml").read_text())
    for key, value in overrides.items():
        params[key] = {**params[key], **value} if isinstance(value, dict) else value
    (workspace / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    with Repo(str(workspace), uninitialized=True) as repo:
        return {
            stage.name: [key for dep in stage.deps if hasattr(dep, "params") for key in dep.params]
            for stage in repo.index.stages
        }


@pytest.mark.parametrize("kind", TOKENIZER_KINDS)
def test_train_tokenizer_tracks_the_selected_kinds_section_and_no_other(tmp_path, kind):
    tracked = tracked_params(tmp_path, tokenizer={"kind": kind}, policies=["next_token"])["train_tokenizer"]
    assert kind_section(kind) in tracked
    others = [kind_section(other) for other in TOKENIZER_KINDS if other != kind]
    assert not set(others) & set(tracked)
    assert "tokenizer" in tracked


def test_register_tokenizer_tracks_the_kind_which_names_the_registered_model(tmp_path):
    assert "tokenizer.kind" in tracked_params(tmp_path)["register_tokenizer"]


def test_params_yaml_has_a_section_for_every_kind():
    """DVC refuses a tracked key missing from params.yaml, so even carp_msvq's empty section must be there."""
    raw = yaml.safe_load((REPO / "params.yaml").read_text())
    for kind in TOKENIZER_KINDS:
        assert kind_section(kind) in raw, kind


def test_the_carp_family_with_another_kind_is_refused_in_one_line_at_params_load():
    raw = yaml.safe_load((REPO / "params.yaml").read_text())
    raw["tokenizer"]["kind"] = "fast"
    with pytest.raises(ConfigError) as raised:
        params_from_dict(raw)
    assert str(raised.value) == (
        "tokenizer.kind='fast': the carp family predicts carp_msvq tokens only; choose another kind or another "
        "family (next_token takes any kind)"
    )


@pytest.mark.parametrize("kind", ["joint_msvq", "binning"])
def test_a_multi_task_carp_policy_with_another_kind_is_refused_too(kind):
    raw = yaml.safe_load((REPO / "params.yaml").read_text())
    raw.update(policies=["next_token"], multitask=["carp"], tasks=["lift", "can"])
    raw["tokenizer"]["kind"] = kind
    with pytest.raises(ConfigError, match=rf"tokenizer.kind='{kind}': the carp family predicts carp_msvq"):
        params_from_dict(raw)


def test_next_token_takes_any_kind_and_the_selected_section_is_at_hand():
    raw = yaml.safe_load((REPO / "params.yaml").read_text())
    raw["policies"] = ["next_token", "diffusion_unet"]
    raw["tokenizer"]["kind"] = "fast"
    raw["tokenizer_fast"]["scale"] = 5.0
    params = params_from_dict(raw)
    assert params.tokenizer_kind_config == params.tokenizer_fast
    assert params.tokenizer_kind_config.scale == 5.0
