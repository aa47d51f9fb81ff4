"""Karras et al.'s EDM noise levels and preconditioning, the Heun sampler, and the losses' weighting.

Follows "Elucidating the Design Space of Diffusion-Based Generative Models" (Karras et al., NeurIPS 2022) as
Consistency Policy's official code (Prasad et al., RSS 2024, `consistency_policy/diffusion.py`) applies it to action
chunks: a chunk is noised as ``x_sigma = x_0 + sigma * noise`` for noise levels sigma in [sigma_min, sigma_max], and
the network F is wrapped into a denoiser

    D(x, sigma) = c_skip(sigma) * x + c_out(sigma) * F(c_in(sigma) * x, c_noise(sigma))

with consistency models' boundary-condition scalings (Song et al., 2023), so that D(x, sigma_min) = x exactly:

    c_skip = sigma_data^2 / ((sigma - sigma_min)^2 + sigma_data^2)
    c_out  = (sigma - sigma_min) * sigma_data / sqrt(sigma^2 + sigma_data^2)
    c_in   = 1 / sqrt(sigma^2 + sigma_data^2)
    c_noise = 250 * ln(sigma)

With sigma_min = 0 these are EDM's own. c_noise is EDM's ln(sigma) / 4, scaled by 1000 as the official code does so
that DP's sinusoidal step embedding, built for integer steps up to 100, sees inputs of that range. The discretization
is EDM's: level i of N is ``(sigma_max^(1/rho) + i / (N - 1) * (sigma_min^(1/rho) - sigma_max^(1/rho)))^rho``.

Deviation from the official code: sampling starts from ``sigma_max * noise``, the initial distribution of the
probability-flow ODE, where the official samplers start from unit-variance noise.
"""

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import torch

NOISE_EMBEDDING_SCALE = 250.0
"""c_noise = NOISE_EMBEDDING_SCALE * ln(sigma): EDM's ln(sigma) / 4 times the official code's 1000."""

HUBER_SCALE = 0.00054
"""iCT's pseudo-Huber constant (Song and Dhariwal, 2023): delta = HUBER_SCALE * sqrt(values per sample)."""

Denoise = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""`denoise(x, sigma)`: the denoised estimate (B, H, A) of noisy chunks x (B, H, A) at noise levels sigma (B,)."""


class Preconditioning(NamedTuple):
    """The scalings of one batch of noise levels, each shaped like the sigma they were computed from."""

    c_skip: torch.Tensor
    c_out: torch.Tensor
    c_in: torch.Tensor
    c_noise: torch.Tensor


@dataclass(frozen=True)
class KarrasSchedule:
    """EDM's noise-level range, discretization and preconditioning.

    Attributes:
        sigma_min: smallest noise level, where the denoiser is the identity; > 0.
        sigma_max: largest noise level, where sampling starts; > sigma_min.
        rho: curvature of the discretization (levels crowd towards sigma_min as rho grows); > 0.
        sigma_data: standard deviation assumed for the normalized actions; > 0.
    """

    sigma_min: float = 0.02
    sigma_max: float = 80.0
    rho: float = 7.0
    sigma_data: float = 0.5

    def preconditioning(self, sigma: torch.Tensor) -> Preconditioning:
        """c_skip, c_out, c_in and c_noise at noise levels `sigma` (any shape, float)."""
        data_variance = self.sigma_data**2
        total_std = (sigma**2 + data_variance).sqrt()
        offset = sigma - self.sigma_min
        return Preconditioning(
            c_skip=data_variance / (offset**2 + data_variance),
            c_out=offset * self.sigma_data / total_std,
            c_in=1.0 / total_std,
            c_noise=NOISE_EMBEDDING_SCALE * sigma.log(),
        )

    def levels(self, indices: torch.Tensor, num_levels: int) -> torch.Tensor:
        """Noise levels at positions `indices` (any shape) of an N = `num_levels` discretization, sigma_max first.

        Positions past N - 1 give sigma_min (the levels are clamped to [sigma_min, sigma_max]).
        """
        start, end = self.sigma_max ** (1 / self.rho), self.sigma_min ** (1 / self.rho)
        fraction = indices.to(torch.float64) / (num_levels - 1)
        sigma = (start + fraction * (end - start)) ** self.rho
        return sigma.clamp(self.sigma_min, self.sigma_max).to(torch.float32)

    def discretization(self, num_levels: int) -> torch.Tensor:
        """(N,) float32 noise levels from sigma_max down to sigma_min."""
        return self.levels(torch.arange(num_levels), num_levels)

    def loss_weight(self, sigma: torch.Tensor) -> torch.Tensor:
        """EDM's loss weight lambda(sigma) = (sigma^2 + sigma_data^2) / (sigma * sigma_data)^2.

        It is EDM's 1 / c_out^2, which gives the network's own regression target unit weight at every level.
        """
        return (sigma**2 + self.sigma_data**2) / (sigma * self.sigma_data) ** 2

    def log_normal_levels(
        self, count: int, mean: float, std: float, generator: torch.Generator | None, device: torch.device
    ) -> torch.Tensor:
        """(count,) training noise levels with ln(sigma) ~ Normal(mean, std) (EDM's P_mean, P_std)."""
        normal = torch.randn(count, generator=generator, device=device)
        return (normal * std + mean).exp()

    def initial_noise(
        self, shape: tuple[int, ...], generator: torch.Generator | None, device: torch.device, dtype: torch.dtype
    ) -> torch.Tensor:
        """Gaussian chunks at sigma_max, where the probability-flow ODE starts."""
        return self.sigma_max * torch.randn(shape, generator=generator, device=device, dtype=dtype)


def expand_like(values: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """(B,) per-sample values viewed as (B, 1, ..., 1) to broadcast against `reference` (B, ...)."""
    return values.reshape(values.shape[0], *([1] * (reference.dim() - 1)))


def heun_step(denoise: Denoise, sample: torch.Tensor, sigma: torch.Tensor, next_sigma: torch.Tensor) -> torch.Tensor:
    """One step of EDM's second-order (Heun) solver of dx/dsigma = (x - D(x, sigma)) / sigma.

    Args:
        denoise: the denoiser.
        sample: (B, H, A) chunks at `sigma`.
        sigma: (B,) current levels, > 0.
        next_sigma: (B,) levels to step to, > 0; a sample whose level does not change is returned unchanged.

    Returns:
        (B, H, A) chunks at `next_sigma`.
    """
    step = expand_like(next_sigma - sigma, sample)
    slope = (sample - denoise(sample, sigma)) / expand_like(sigma, sample)
    euler = sample + step * slope
    next_slope = (euler - denoise(euler, next_sigma)) / expand_like(next_sigma, sample)
    return sample + step * (slope + next_slope) / 2


def heun_sample(denoise: Denoise, sample: torch.Tensor, sigmas: torch.Tensor) -> torch.Tensor:
    """Integrate the probability-flow ODE through the levels `sigmas` (N,) with Heun steps (2 (N - 1) calls).

    Args:
        denoise: the denoiser.
        sample: (B, H, A) chunks at `sigmas[0]`.
        sigmas: (N,) decreasing positive levels.

    Returns:
        (B, H, A) chunks at `sigmas[-1]`.
    """
    batch = sample.shape[0]
    for sigma, next_sigma in zip(sigmas[:-1], sigmas[1:]):
        sample = heun_step(denoise, sample, sigma.expand(batch), next_sigma.expand(batch))
    return sample


def pseudo_huber(prediction: torch.Tensor, target: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """The official code's loss: mean of ``sqrt(e^4 + delta^2) - delta`` over the squared errors e^2 (scalar).

    delta = HUBER_SCALE * sqrt(H * A) (iCT's constant for the chunk's size); the loss is the squared error where it
    is large against delta and grows as e^4 / (2 delta) below. As in the official code it is taken of the squared
    error, not of the error as in iCT.

    Args:
        prediction: (B, H, A).
        target: (B, H, A).
        weights: (B,) per-sample weights, or None.
    """
    delta = HUBER_SCALE * math.sqrt(math.prod(prediction.shape[1:]))
    squared = (prediction - target) ** 2
    loss = (squared**2 + delta**2).sqrt() - delta
    if weights is not None:
        loss = loss * expand_like(weights, loss)
    return loss.mean()
