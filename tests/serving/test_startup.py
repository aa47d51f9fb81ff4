import pytest

from carp import cli
from carp.config import DataConfig, Params
from carp.policies.carp.config import CarpInference
from carp.serving.startup import ServingStartError, load_served_model
from tests.serving.conftest import PROTOCOL, SPEC, save_tiny_checkpoint


def test_a_checkpoint_that_records_its_protocol_is_served_without_params(checkpoint):
    model, spec = load_served_model(checkpoint)
    assert spec == SPEC
    assert model.inference == {"top_k": 1}  # the CARP family's default: greedy


def test_params_choose_the_inference_settings_but_not_the_recorded_spec(checkpoint):
    params = Params(data=DataConfig(obs_steps=1), inference={"carp": CarpInference(top_k=3)})
    model, spec = load_served_model(checkpoint, params)
    assert spec == SPEC and model.inference == {"top_k": 3} and model.policy.top_k == 3


def test_a_checkpoint_without_the_protocol_needs_the_params_it_was_trained_with(tmp_path):
    old = save_tiny_checkpoint(tmp_path / "old.pt", serving=None)
    with pytest.raises(ServingStartError, match="does not record its serving protocol.*pass --params"):
        load_served_model(old)
    _, spec = load_served_model(old, Params(data=DataConfig(obs_keys=("object", "robot0_eef_pos"))))
    assert spec.obs_keys == SPEC.obs_keys and spec.obs_widths is None  # requests must send the concatenated obs
    assert (spec.obs_steps, spec.action_horizon, spec.action_steps) == (2, 16, 8)


def test_a_recorded_protocol_that_does_not_fit_the_policy_is_refused(tmp_path):
    wrong = save_tiny_checkpoint(tmp_path / "wrong.pt", serving=PROTOCOL | {"obs_widths": [1, 3]})
    with pytest.raises(ServingStartError, match=r"obs_widths \[1, 3\] of keys \['object', 'robot0_eef_pos'\] do not"):
        load_served_model(wrong)
    future = save_tiny_checkpoint(tmp_path / "future.pt", serving=PROTOCOL | {"format": 2})
    with pytest.raises(ServingStartError, match="serving protocol format 2, this carp reads 1"):
        load_served_model(future)


def test_serve_without_params_for_an_old_checkpoint_prints_one_error_line(tmp_path, capsys):
    old = save_tiny_checkpoint(tmp_path / "old.pt", serving=None)
    with pytest.raises(SystemExit) as exited:
        cli.main(["serve", "--model", str(old)])
    assert exited.value.code == 1
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {old}: the checkpoint does not record its serving protocol")
