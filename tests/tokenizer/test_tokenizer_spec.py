import pytest

from carp.tokenizer.spec import TokenizerSpec


def test_defaults_match_design():
    spec = TokenizerSpec(action_dim=10)
    assert spec.action_horizon == 16
    assert spec.scales == (1, 2, 3, 4)
    assert (spec.codebook_size, spec.latent_channels, spec.base_channels) == (512, 8, 2)
    assert spec.channel_mult == (2, 4)
    assert spec.commitment_weight == 0.25
    assert spec.latent_length == 4
    assert spec.num_scales == 4
    assert spec.tokens_per_chunk == 100


def test_round_trip_through_dict_and_lists_become_tuples():
    spec = TokenizerSpec(action_dim=7, scales=[1, 2, 4], codebook_size=64)
    values = spec.to_dict()
    assert values["scales"] == [1, 2, 4]
    restored = TokenizerSpec.from_dict(values)
    assert restored == spec
    assert restored.scales == (1, 2, 4)
    assert hash(restored) == hash(spec)


def test_from_dict_rejects_unknown_keys():
    with pytest.raises(ValueError, match=r"unknown TokenizerSpec keys: \['depth'\]"):
        TokenizerSpec.from_dict({"action_dim": 2, "depth": 3})


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"scales": (1, 2, 17)}, r"scales must end at most at the action horizon 16 .*, got last scale 17"),
        ({"codebook_size": 1}, r"codebook_size must be >= 2, got 1"),
        ({"action_dim": 0}, r"action_dim must be >= 1, got 0"),
        ({"scales": (1, 3, 2, 4)}, r"scales must be strictly increasing, got \[1, 3, 2, 4\]"),
        ({"scales": (2, 2, 4)}, r"scales must be strictly increasing"),
        ({"scales": ()}, r"scales must contain at least one scale"),
        ({"scales": (0, 4)}, r"scales entries must be >= 1"),
        ({"action_horizon": 18}, r"action_horizon \(18\) must be divisible by 2 \*\* len\(channel_mult\) = 4"),
        ({"latent_channels": 2.5}, r"latent_channels must be an integer"),
        ({"codebook_size": True}, r"codebook_size must be an integer"),
        ({"commitment_weight": -0.1}, r"commitment_weight must be >= 0"),
        ({"channel_mult": ()}, r"channel_mult must name at least one"),
    ],
)
def test_invalid_specs_name_the_field(overrides, message):
    values = {"action_dim": 10, **overrides}
    with pytest.raises(ValueError, match=message):
        TokenizerSpec(**values)


def test_other_horizons_change_the_latent_length():
    spec = TokenizerSpec(action_dim=1, action_horizon=32, scales=(1, 2, 4, 8), channel_mult=(2, 4))
    assert spec.latent_length == 8
    assert TokenizerSpec(action_dim=1, action_horizon=16, scales=(2, 8), channel_mult=(2,)).latent_length == 8


@pytest.mark.parametrize(
    ("scales", "latent_length"), [((1,), 4), ((1, 2, 3), 4), ((1, 2, 3, 4), 4), ((1, 2, 3, 4, 5), 5), ((2, 6), 6)]
)
def test_the_latent_is_the_encoders_length_or_the_last_scale_where_longer(scales, latent_length):
    spec = TokenizerSpec(action_dim=2, scales=scales)
    assert (spec.encoder_length, spec.latent_length) == (4, latent_length)
    assert spec.tokens_per_chunk == 2 * sum(scales) and spec.num_scales == len(scales)
