import pytest

from carp.policies.carp.config import CarpConfig
from carp.policies.carp.spec import PolicySpec
from tests.policies.carp.factories import tiny_policy_spec


def test_derived_sizes_of_default_config():
    spec = PolicySpec(obs_dim=19, obs_steps=2, action_dim=10, scales=[1, 2, 3, 4], latent_channels=8, codebook_size=512)
    assert spec.scales == (1, 2, 3, 4)
    assert spec.sequence_length == 100
    assert spec.num_scales == 4
    assert spec.condition_features == 38
    assert spec.config.hidden_width == 256
    assert spec.config == CarpConfig()  # the architecture is the params section's, defaults included


def test_specs_of_earlier_checkpoints_load_single_task_and_refuse_an_internal_task_embedding():
    values = tiny_policy_spec().to_dict()
    assert "num_tasks" not in values
    assert PolicySpec.from_dict(values | {"num_tasks": 0}) == tiny_policy_spec()
    with pytest.raises(ValueError, match="num_tasks > 0: a multi-task transformer of an earlier format"):
        PolicySpec.from_dict(values | {"num_tasks": 2})


def test_dict_round_trip_and_unknown_keys():
    spec = tiny_policy_spec()
    assert PolicySpec.from_dict(spec.to_dict()) == spec
    assert spec.to_dict()["config"]["width"] == 16 and spec.to_dict()["scales"] == [1, 2]
    with pytest.raises(ValueError, match="unknown PolicySpec keys: \\['heads'\\]"):
        PolicySpec.from_dict(spec.to_dict() | {"heads": 4})
    with pytest.raises(TypeError, match="heads"):
        PolicySpec.from_dict(spec.to_dict() | {"config": {"heads": 4}})


def test_a_flat_spec_of_an_older_checkpoint_reads_its_architecture_into_the_config():
    spec = tiny_policy_spec(dropout=0.1)
    flat = {key: value for key, value in spec.to_dict().items() if key != "config"}
    flat |= {"depth": 1, "width": 16, "num_heads": 2, "mlp_ratio": 4.0, "dropout": 0.1}
    assert PolicySpec.from_dict(flat) == PolicySpec(
        **(spec.to_dict() | {"config": CarpConfig(**spec.to_dict()["config"])})
    )
    with pytest.raises(ValueError, match="PolicySpec keys \\['width'\\] belong in its config"):
        PolicySpec.from_dict(spec.to_dict() | {"width": 16})


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"scales": (2, 1)}, "strictly increasing"),
        ({"scales": ()}, "must not be empty"),
        ({"width": 10, "num_heads": 4}, "carp.num_heads=4: must divide width=10"),
        ({"codebook_size": 1}, "codebook_size must be an integer >= 2"),
        ({"depth": 0}, "carp.depth=0: must be an integer >= 1"),
        ({"obs_steps": True}, "obs_steps must be a positive integer"),
        ({"dropout": 1.0}, "carp.dropout=1.0: must be in"),
        ({"mlp_ratio": 0}, "carp.mlp_ratio=0: must be > 0"),
    ],
)
def test_invalid_specs_are_rejected(overrides, message):
    with pytest.raises(ValueError, match=message):
        tiny_policy_spec(**overrides)


def test_the_config_must_be_carps_section():
    with pytest.raises(ValueError, match="PolicySpec.config must be a CarpConfig, got dict"):
        PolicySpec(obs_dim=3, obs_steps=2, action_dim=2, scales=(1, 2), latent_channels=4, codebook_size=8, config={})
