import pytest

from carp.policies.carp.spec import PolicySpec
from tests.policies.carp.factories import tiny_policy_spec


def test_derived_sizes_of_default_config():
    spec = PolicySpec(obs_dim=19, obs_steps=2, action_dim=10, scales=[1, 2, 3, 4], latent_channels=8, codebook_size=512)
    assert spec.scales == (1, 2, 3, 4)
    assert spec.sequence_length == 100
    assert spec.num_scales == 4
    assert spec.condition_features == 38
    assert spec.hidden_width == 256
    assert (spec.depth, spec.width, spec.num_heads) == (8, 64, 8)


def test_task_embedding_widens_condition():
    assert tiny_policy_spec(num_tasks=3).condition_features == 2 * 3 + 3


def test_dict_round_trip_and_unknown_keys():
    spec = tiny_policy_spec(num_tasks=2)
    assert PolicySpec.from_dict(spec.to_dict()) == spec
    with pytest.raises(ValueError, match="unknown PolicySpec keys: \\['heads'\\]"):
        PolicySpec.from_dict(spec.to_dict() | {"heads": 4})


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"scales": (2, 1)}, "strictly increasing"),
        ({"scales": ()}, "must not be empty"),
        ({"width": 10, "num_heads": 4}, "divisible by num_heads"),
        ({"codebook_size": 1}, "codebook_size must be an integer >= 2"),
        ({"depth": 0}, "depth must be a positive integer"),
        ({"obs_steps": True}, "obs_steps must be a positive integer"),
        ({"num_tasks": -1}, "num_tasks must be a non-negative integer"),
        ({"dropout": 1.0}, "dropout must be in"),
        ({"mlp_ratio": 0}, "mlp_ratio must be positive"),
    ],
)
def test_invalid_specs_are_rejected(overrides, message):
    with pytest.raises(ValueError, match=message):
        tiny_policy_spec(**overrides)
