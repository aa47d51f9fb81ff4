"""EDM's preconditioning identities, its discretization, the Heun solver against an exact ODE solution, the loss."""

import math

import pytest
import torch

from carp.policies.consistency.karras import KarrasSchedule, heun_sample, heun_step, pseudo_huber

SIGMAS = torch.tensor([0.02, 0.1, 0.5, 1.0, 5.0, 80.0], dtype=torch.float64)


def test_the_denoiser_is_the_identity_at_sigma_min():
    schedule = KarrasSchedule()
    scalings = schedule.preconditioning(torch.tensor([schedule.sigma_min], dtype=torch.float64))
    assert scalings.c_skip.item() == pytest.approx(1.0, abs=1e-12)
    assert scalings.c_out.item() == pytest.approx(0.0, abs=1e-12)
    # Away from sigma_min the network's output matters and the skip fades.
    high = schedule.preconditioning(torch.tensor([80.0], dtype=torch.float64))
    assert high.c_skip.item() < 1e-4 and high.c_out.item() == pytest.approx(0.5 * (80 - 0.02) / math.hypot(80, 0.5))


def test_edm_scalings_give_unit_input_and_target_variance():
    """With sigma_min = 0 the scalings are EDM's: network input and regression target have unit variance."""
    schedule = KarrasSchedule(sigma_min=0.0, sigma_data=0.5)
    c_skip, c_out, c_in, c_noise = schedule.preconditioning(SIGMAS)
    data_variance = 0.25
    torch.testing.assert_close(c_in**2 * (SIGMAS**2 + data_variance), torch.ones_like(SIGMAS))
    # Target F = (x_0 - c_skip (x_0 + sigma n)) / c_out: variance ((1 - c_skip)^2 s_d^2 + c_skip^2 sigma^2) / c_out^2.
    target_variance = ((1 - c_skip) ** 2 * data_variance + c_skip**2 * SIGMAS**2) / c_out**2
    torch.testing.assert_close(target_variance, torch.ones_like(SIGMAS))
    torch.testing.assert_close(schedule.loss_weight(SIGMAS), 1 / c_out**2)
    torch.testing.assert_close(c_noise, 250 * SIGMAS.log())


def test_the_discretization_runs_from_sigma_max_to_sigma_min():
    schedule = KarrasSchedule()
    levels = schedule.discretization(80)
    assert levels[0].item() == pytest.approx(80.0) and levels[-1].item() == pytest.approx(0.02)
    assert bool((levels[1:] < levels[:-1]).all())
    # The official three-step chain's positions 27 and 54 of 80.
    chain = schedule.levels(torch.tensor([27, 54]), 80)
    torch.testing.assert_close(chain, torch.tensor([12.02, 0.884]), rtol=2e-3, atol=0)
    assert schedule.levels(torch.tensor([80]), 80).item() == pytest.approx(0.02)


def gaussian_denoiser(data_std: float):
    """The exact denoiser E[x_0 | x_sigma] = x s^2 / (s^2 + sigma^2) of data x_0 ~ Normal(0, s^2)."""

    def denoise(noisy: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
        variance = data_std**2
        return noisy * (variance / (variance + sigma**2)).reshape(-1, 1, 1)

    return denoise


def test_heun_steps_follow_the_exact_probability_flow_of_gaussian_data():
    """For Gaussian data the ODE's solution is x(sigma) = x(sigma_0) sqrt(s^2 + sigma^2) / sqrt(s^2 + sigma_0^2)."""
    data_std = 0.5
    schedule = KarrasSchedule(sigma_data=data_std)
    start = torch.randn(64, 4, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 80.0
    exact = start * math.sqrt(data_std**2 + 0.02**2) / math.sqrt(data_std**2 + 80.0**2)
    errors = []
    for num_levels in (40, 80, 200):
        end = heun_sample(gaussian_denoiser(data_std), start, schedule.discretization(num_levels).double())
        errors.append(((end - exact).abs() / exact.abs()).max().item())
    assert errors[-1] < 1e-3
    # Second order: doubling the levels divides the error by about four.
    assert 3.0 < errors[0] / errors[1] < 5.0


def test_a_step_to_the_same_level_leaves_the_sample_unchanged():
    sample = torch.randn(3, 4, 2)
    level = torch.full((3,), 0.5)
    torch.testing.assert_close(heun_step(gaussian_denoiser(0.5), sample, level, level), sample)


def test_pseudo_huber_is_the_squared_error_far_above_delta_and_quartic_below():
    prediction = torch.zeros(1, 16, 10)
    delta = 0.00054 * math.sqrt(160)
    large = pseudo_huber(prediction, torch.ones(1, 16, 10))
    assert large.item() == pytest.approx(math.sqrt(1 + delta**2) - delta)
    small_error = 0.01
    small = pseudo_huber(prediction, torch.full((1, 16, 10), small_error))
    assert small.item() == pytest.approx(small_error**4 / (2 * delta), rel=1e-3)
    weighted = pseudo_huber(torch.zeros(2, 16, 10), torch.ones(2, 16, 10), torch.tensor([1.0, 3.0]))
    assert weighted.item() == pytest.approx(2 * large.item(), rel=1e-6)
