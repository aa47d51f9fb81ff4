import pytest

from carp.config import ConfigError, params_from_dict
from carp.policies.diffusion.config import DiffusionTransformerConfig, DiffusionUNetConfig, DiffusionUNetSampling


def test_defaults_are_diffusion_policys_lowdim_recipes():
    unet = DiffusionUNetConfig()
    assert unet.down_dims == (256, 512, 1024)
    assert (unet.kernel_size, unet.num_groups, unet.step_embedding_dim) == (5, 8, 256)
    assert unet.num_train_steps == 100
    sampling = DiffusionUNetSampling()
    assert (sampling.sampler, sampling.num_inference_steps) == ("ddpm", 100)
    assert sampling.settings_for("lift") == {"sampler": "ddpm", "num_inference_steps": 100}
    assert unet.horizon_multiple == 4
    transformer = DiffusionTransformerConfig()
    assert (transformer.num_layers, transformer.num_heads, transformer.width) == (8, 4, 256)
    assert (transformer.weight_decay, transformer.warmup_steps) == (1e-3, 1000)


def test_down_dims_from_yaml_list_become_a_tuple():
    config = DiffusionUNetConfig(down_dims=[64, 128, 256])
    assert config.down_dims == (64, 128, 256)
    assert hash(config)


@pytest.mark.parametrize(
    ("factory", "overrides", "message"),
    [
        (DiffusionUNetConfig, {"num_groups": 7}, "diffusion_unet.num_groups=7: must divide every entry of down_dims"),
        (DiffusionUNetConfig, {"kernel_size": 4}, "diffusion_unet.kernel_size=4: must be odd"),
        (DiffusionUNetConfig, {"down_dims": ()}, "diffusion_unet.down_dims=(): must name at least one level"),
        (DiffusionUNetConfig, {"step_embedding_dim": 6.0}, "diffusion_unet.step_embedding_dim=6.0: must be an integer"),
        (
            DiffusionUNetSampling,
            {"sampler": "euler"},
            "inference.diffusion_unet.sampler='euler': must be one of ('ddpm', 'ddim')",
        ),
        (DiffusionUNetConfig, {"ema_max_decay": 1.0}, "diffusion_unet.ema_max_decay=1.0: must be in [0, 1)"),
        (DiffusionUNetConfig, {"use_ema": "yes"}, "diffusion_unet.use_ema='yes': must be true or false"),
        (DiffusionTransformerConfig, {"num_heads": 3}, "diffusion_transformer.num_heads=3: must divide width=256"),
        (
            DiffusionTransformerConfig,
            {"attention_dropout": 1.0},
            "diffusion_transformer.attention_dropout=1.0: must be in [0, 1)",
        ),
        (DiffusionTransformerConfig, {"learning_rate": 0.0}, "diffusion_transformer.learning_rate=0.0: must be > 0"),
    ],
)
def test_bad_values_are_refused_with_the_dotted_key(factory, overrides, message):
    with pytest.raises(ConfigError) as error:
        factory(**overrides)
    assert str(error.value).startswith(message)


def test_inference_steps_beyond_the_training_schedule_are_refused_with_both_keys_named():
    raw = {"diffusion_unet": {"num_train_steps": 50}, "inference": {"diffusion_unet": {"num_inference_steps": 51}}}
    with pytest.raises(ConfigError, match=r"inference.diffusion_unet.num_inference_steps=51: must be at most "
                       r"diffusion_unet.num_train_steps=50"):  # fmt: skip
        params_from_dict(raw)
