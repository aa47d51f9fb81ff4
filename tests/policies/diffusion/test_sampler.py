import pytest
import torch
from torch import nn

from carp.policies.diffusion.config import DiffusionUNetConfig, SamplingConfig
from carp.policies.diffusion.sampler import DiffusionSampler
from carp.policies.diffusion.unet import ConditionalUNet1D

OBS_STEPS, OBS_DIM, ACTION_DIM, HORIZON = 2, 4, 3, 8
TINY = DiffusionUNetConfig(down_dims=(16, 32), kernel_size=3, num_groups=8, step_embedding_dim=16)


def _tiny_unet() -> ConditionalUNet1D:
    torch.manual_seed(0)
    return ConditionalUNet1D(TINY, ACTION_DIM, OBS_DIM, OBS_STEPS).eval()


class ConstantNoise(nn.Module):
    """A denoiser that predicts the same (large) noise everywhere and counts its calls."""

    action_dim = ACTION_DIM

    def __init__(self, value: float) -> None:
        super().__init__()
        self.value = value
        self.calls = 0

    def prepare(self, obs_features, steps, action_horizon):
        return None

    def predict_noise(self, noisy_actions, condition, step_index):
        self.calls += 1
        return torch.full_like(noisy_actions, self.value)


def test_inference_steps_cover_the_schedule_in_descending_order():
    ddpm = DiffusionSampler(100, "ddpm", 100)
    assert torch.equal(ddpm.steps, torch.arange(99, -1, -1))
    ddim = DiffusionSampler(100, "ddim", 10)
    assert ddim.steps.tolist() == [90, 80, 70, 60, 50, 40, 30, 20, 10, 0]
    assert (ddpm.description, ddim.description) == ("DDPM-100", "DDIM-10")


@pytest.mark.parametrize(("sampler", "steps"), [("ddpm", 100), ("ddim", 10), ("ddim", 1)])
def test_one_denoiser_call_per_step_and_samples_clipped_to_the_action_range(sampler, steps):
    denoiser = ConstantNoise(-25.0)
    chunk = DiffusionSampler(100, sampler, steps).sample(denoiser, torch.zeros(5, OBS_STEPS, OBS_DIM), HORIZON)
    assert denoiser.calls == steps
    assert chunk.shape == (5, HORIZON, ACTION_DIM)
    # The last step returns the clipped estimate of the clean chunk (no noise is left at step 0).
    assert chunk.abs().max() == pytest.approx(1.0, abs=1e-4)


def test_seeded_ddim_sample_is_deterministic():
    unet = _tiny_unet()
    sampler = DiffusionSampler(100, "ddim", 10)
    obs = torch.randn(3, OBS_STEPS, OBS_DIM, generator=torch.Generator().manual_seed(0))
    first = sampler.sample(unet, obs, HORIZON, torch.Generator().manual_seed(7))
    second = sampler.sample(unet, obs, HORIZON, torch.Generator().manual_seed(7))
    other_seed = sampler.sample(unet, obs, HORIZON, torch.Generator().manual_seed(8))
    assert torch.equal(first, second)
    assert not torch.allclose(first, other_seed)


def test_seeded_ddpm_sample_is_deterministic_though_every_step_draws_noise():
    unet = _tiny_unet()
    sampler = DiffusionSampler(100, "ddpm", 20)
    obs = torch.zeros(2, OBS_STEPS, OBS_DIM)
    first = sampler.sample(unet, obs, HORIZON, torch.Generator().manual_seed(3))
    second = sampler.sample(unet, obs, HORIZON, torch.Generator().manual_seed(3))
    assert torch.equal(first, second)


def test_noisy_batch_follows_the_closed_form_of_the_forward_process():
    sampler = DiffusionSampler()
    actions = torch.rand(64, HORIZON, ACTION_DIM) * 2 - 1
    batch = sampler.noisy_batch(actions, torch.Generator().manual_seed(0))
    assert batch.steps.min() >= 0 and batch.steps.max() < 100
    signal = sampler.training_scheduler.alphas_cumprod[batch.steps].view(-1, 1, 1)
    expected = signal.sqrt() * actions + (1 - signal).sqrt() * batch.noise
    torch.testing.assert_close(batch.noisy_actions, expected)


def test_squared_cosine_schedule_nearly_destroys_the_signal_by_the_last_step():
    alphas_cumprod = DiffusionSampler().training_scheduler.alphas_cumprod
    assert alphas_cumprod[0] > 0.99
    assert alphas_cumprod[-1] < 1e-3
    assert (alphas_cumprod[1:] < alphas_cumprod[:-1]).all()


@pytest.mark.parametrize(
    ("arguments", "message"),
    [((100, "euler", 10), "sampler must be one of"), ((100, "ddim", 0), r"num_inference_steps must be in \[1, ")],
)
def test_bad_sampler_settings_are_refused(arguments, message):
    with pytest.raises(ValueError, match=message):
        DiffusionSampler(*arguments)


def test_trained_denoiser_produces_both_modes_where_a_regressor_averages_them():
    # Given the same observation, the whole chunk is +1 or -1 with equal probability. A one-level U-Net keeps the
    # few hundred training steps within a few seconds on one CPU thread.
    torch.manual_seed(0)
    horizon, batch = 4, 64
    config = DiffusionUNetConfig(down_dims=(16,), kernel_size=3, num_groups=8, step_embedding_dim=16)
    denoiser = ConditionalUNet1D(config, action_dim=1, obs_dim=1, obs_steps=1)
    regressor = nn.Sequential(nn.Linear(1, 32), nn.Mish(), nn.Linear(32, horizon))
    sampler = DiffusionSampler.from_config(config, SamplingConfig(sampler="ddim", num_inference_steps=10))
    generator = torch.Generator().manual_seed(0)
    obs = torch.zeros(batch, 1, 1)
    denoiser_optimizer = torch.optim.AdamW(denoiser.parameters(), lr=3e-3)
    regressor_optimizer = torch.optim.AdamW(regressor.parameters(), lr=3e-3)
    for _ in range(200):
        signs = torch.randint(0, 2, (batch, 1, 1), generator=generator) * 2.0 - 1.0
        actions = signs.expand(batch, horizon, 1)
        for optimizer, loss in (
            (denoiser_optimizer, sampler.training_loss(denoiser, actions, obs, generator)),
            (regressor_optimizer, nn.functional.mse_loss(regressor(obs[:, 0]), actions[..., 0])),
        ):
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()

    chunks = sampler.sample(denoiser.eval(), torch.zeros(200, 1, 1), horizon, torch.Generator().manual_seed(1))
    chunk_means = chunks.mean(dim=(1, 2))  # (200,)
    assert (chunk_means > 0.8).float().mean() > 0.25
    assert (chunk_means < -0.8).float().mean() > 0.25
    assert (chunk_means.abs() < 0.5).float().mean() < 0.15
    with torch.no_grad():
        regressed = regressor(torch.zeros(1, 1))
    assert regressed.abs().max() < 0.2
