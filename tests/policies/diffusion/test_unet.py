import pytest
import torch

from carp.policies.diffusion.config import DiffusionUNetConfig
from carp.policies.diffusion.unet import ConditionalUNet1D

CAN_OBS_DIM, OBS_STEPS, ACTION_DIM = 23, 2, 10
TINY = DiffusionUNetConfig(down_dims=(16, 32, 64), kernel_size=3, num_groups=8, step_embedding_dim=16)


def _count(model: torch.nn.Module) -> int:
    return sum(parameter.numel() for parameter in model.parameters())


def _tiny_unet(seed: int = 0) -> ConditionalUNet1D:
    torch.manual_seed(seed)
    return ConditionalUNet1D(TINY, action_dim=3, obs_dim=4, obs_steps=OBS_STEPS).eval()


def test_paper_size_for_can_has_65_9_million_parameters():
    unet = ConditionalUNet1D(DiffusionUNetConfig(), ACTION_DIM, CAN_OBS_DIM, OBS_STEPS)
    assert _count(unet) == pytest.approx(65.9e6, rel=0.01)


def test_width_is_a_config_value():
    narrow = ConditionalUNet1D(DiffusionUNetConfig(down_dims=(64, 128, 256)), ACTION_DIM, CAN_OBS_DIM, OBS_STEPS)
    assert narrow.down_levels[0].first.first[0].out_channels == 64
    assert narrow.middle[0].first[0].in_channels == 256
    assert _count(narrow) == pytest.approx(5.44e6, rel=0.01)


@pytest.mark.parametrize("horizon", [4, 8, 16, 20, 32])
def test_output_has_the_shape_of_the_noisy_actions(horizon):
    unet = _tiny_unet()
    noisy = torch.randn(2, horizon, 3)
    with torch.no_grad():
        noise = unet(noisy, torch.tensor([3, 70]), torch.randn(2, OBS_STEPS, 4))
    assert noise.shape == noisy.shape
    assert torch.isfinite(noise).all()


@pytest.mark.parametrize("horizon", [6, 10, 2])
def test_horizons_not_divisible_by_four_are_refused(horizon):
    with pytest.raises(ValueError, match=f"H={horizon} must be a positive multiple of 4"):
        _tiny_unet()(torch.randn(1, horizon, 3), torch.tensor([0]), torch.randn(1, OBS_STEPS, 4))


def test_wrong_observation_shape_is_refused():
    with pytest.raises(ValueError, match=r"\(B, To, Do\) = \(B, 2, 4\), got \(1, 3, 4\)"):
        _tiny_unet()(torch.randn(1, 8, 3), torch.tensor([0]), torch.randn(1, 3, 4))


def test_prepared_inference_equals_the_training_forward():
    unet = _tiny_unet()
    for parameter in unet.parameters():  # larger weights so that every FiLM term matters
        parameter.data.normal_(0.0, 0.3)
    obs, noisy = torch.randn(3, OBS_STEPS, 4), torch.randn(3, 16, 3)
    steps = torch.tensor([99, 50, 7, 0])
    with torch.no_grad():
        condition = unet.prepare(obs, steps, 16)
        for index, step in enumerate(steps):
            prepared = unet.predict_noise(noisy, condition, index)
            direct = unet(noisy, step.repeat(3), obs)
            torch.testing.assert_close(prepared, direct, rtol=1e-4, atol=1e-5)


def test_prediction_depends_on_step_and_observations():
    unet = _tiny_unet()
    obs, noisy = torch.randn(2, OBS_STEPS, 4), torch.randn(2, 8, 3)
    with torch.no_grad():
        reference = unet(noisy, torch.tensor([10, 10]), obs)
        other_step = unet(noisy, torch.tensor([90, 90]), obs)
        other_obs = unet(noisy, torch.tensor([10, 10]), obs + 1.0)
    assert (reference - other_step).abs().max() > 1e-4
    assert (reference - other_obs).abs().max() > 1e-4
