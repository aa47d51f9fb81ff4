"""The `vq_bet` and `inference.vq_bet` sections: defaults as in params.yaml, refusals naming the key."""

import pytest

from carp.config import ConfigError, params_from_dict
from carp.policies.vq_bet.config import VqBetConfig, VqBetInference


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"num_codes": 1}, "vq_bet.num_codes=1: must be an integer >= 2"),
        ({"width": 120, "num_heads": 7}, "vq_bet.num_heads=7: must divide width=120"),
        ({"codebook_decay": 1.0}, "vq_bet.codebook_decay=1.0: must be in (0, 1)"),
        ({"freeze_fraction": 0.0}, "vq_bet.freeze_fraction=0.0: must be in (0, 1]"),
        ({"offset_weight": -1.0}, "vq_bet.offset_weight=-1.0: must be >= 0"),
        ({"vq_training_steps": 0}, "vq_bet.vq_training_steps=0: must be an integer >= 1"),
        ({"learning_rate": 0.0}, "vq_bet.learning_rate=0.0: must be > 0"),
    ],
)
def test_bad_settings_are_refused_by_key(settings, message):
    with pytest.raises(ConfigError) as error:
        VqBetConfig(**settings)
    assert str(error.value).startswith(message)


def test_inference_section_and_params_loading():
    assert VqBetInference().settings_for("pusht") == {"code_choice": "sample"}
    with pytest.raises(ConfigError, match="inference.vq_bet.code_choice='top-3': must be one of"):
        VqBetInference(code_choice="top-3")
    params = params_from_dict({"policies": ["vq_bet"], "vq_bet": {"depth": 2}, "inference": {"vq_bet": {}}})
    assert params.family_config("vq_bet") == VqBetConfig(depth=2)
    assert params.inference["vq_bet"] == VqBetInference()
