"""Training noise and DDPM/DDIM inference for the Diffusion Policy denoisers, on `diffusers`' schedulers.

The schedule is DP's (its lowdim workspace configs): `num_train_steps` (100) steps with squared-cosine betas
(`squaredcos_cap_v2`), epsilon prediction, the denoised estimate clipped to [-1, 1] at every step, DDPM variance
`fixed_small`; DDIM with `set_alpha_to_one` and no step offset, eta = 0. Training draws one step per sample uniformly
and regresses the added noise (mean-squared error). Inference starts from Gaussian noise and calls the denoiser once
per sampler step: the denoiser precomputes what does not change between steps (`prepare`), so the loop holds one
denoiser call and one scheduler update per step.
"""

from typing import Any, NamedTuple, Protocol

import torch
import torch.nn.functional as F
from diffusers import DDIMScheduler, DDPMScheduler

from carp.policies.diffusion.config import SAMPLERS, DenoisingConfig, SamplingConfig

BETA_SCHEDULE = "squaredcos_cap_v2"
CLIP_RANGE = 1.0
"""Normalized actions lie in [-1, 1]; each step clips its estimate of the clean chunk to that range."""


class Denoiser(Protocol):
    """What the sampler needs of a denoiser.

    Implemented by :class:`~carp.policies.diffusion.unet.ConditionalUNet1D` and
    :class:`~carp.policies.diffusion.transformer.DiffusionTransformer`.
    """

    action_dim: int

    def __call__(self, noisy_actions: torch.Tensor, steps: torch.Tensor, obs_features: torch.Tensor) -> torch.Tensor:
        """Noise (B, H, A) of noisy actions (B, H, A) at per-sample steps (B,) given observations (B, To, Do)."""
        ...

    def prepare(self, obs_features: torch.Tensor, steps: torch.Tensor, action_horizon: int) -> Any:
        """Per-chunk conditioning for the sampler steps `steps` (N,)."""
        ...

    def predict_noise(self, noisy_actions: torch.Tensor, condition: Any, step_index: int) -> torch.Tensor:
        """Noise (B, H, A) at the `step_index`-th of the prepared steps."""
        ...


class NoisyBatch(NamedTuple):
    """A training batch with noise added.

    Attributes:
        noisy_actions: (B, H, A) actions noised to their step.
        steps: (B,) long diffusion step of each sample, uniform in [0, num_train_steps).
        noise: (B, H, A) the Gaussian noise that was added (the regression target).
    """

    noisy_actions: torch.Tensor
    steps: torch.Tensor
    noise: torch.Tensor


class DiffusionSampler:
    """DP's noise schedule for training and its DDPM or DDIM sampler for inference.

    Args:
        num_train_steps: diffusion steps of the training schedule.
        sampler: `ddpm` or `ddim`.
        num_inference_steps: denoiser calls per chunk, in [1, num_train_steps].
    """

    def __init__(self, num_train_steps: int = 100, sampler: str = "ddpm", num_inference_steps: int = 100) -> None:
        if sampler not in SAMPLERS:
            raise ValueError(f"sampler must be one of {SAMPLERS}, got {sampler!r}")
        if not 1 <= num_inference_steps <= num_train_steps:
            raise ValueError(
                f"num_inference_steps must be in [1, num_train_steps={num_train_steps}], got {num_inference_steps}"
            )
        self.num_train_steps = num_train_steps
        self.sampler = sampler
        self.num_inference_steps = num_inference_steps
        self.training_scheduler = self._ddpm()
        self.inference_scheduler = self._ddpm() if sampler == "ddpm" else self._ddim()
        self.inference_scheduler.set_timesteps(num_inference_steps)
        self.steps = self.inference_scheduler.timesteps.clone()  # (N,) long, descending
        # Each step's loop variable is a 0-d tensor, as diffusers' own pipelines pass it; extracted once here.
        self._step_values = tuple(self.steps.unbind(0))

    @classmethod
    def from_config(cls, config: DenoisingConfig, sampling: SamplingConfig) -> "DiffusionSampler":
        """The sampler of a family's config (training schedule) and inference section (sampler, steps)."""
        return cls(config.num_train_steps, sampling.sampler, sampling.num_inference_steps)

    def _ddpm(self) -> DDPMScheduler:
        return DDPMScheduler(
            num_train_timesteps=self.num_train_steps,
            beta_schedule=BETA_SCHEDULE,
            variance_type="fixed_small",
            clip_sample=True,
            clip_sample_range=CLIP_RANGE,
            prediction_type="epsilon",
        )

    def _ddim(self) -> DDIMScheduler:
        return DDIMScheduler(
            num_train_timesteps=self.num_train_steps,
            beta_schedule=BETA_SCHEDULE,
            clip_sample=True,
            clip_sample_range=CLIP_RANGE,
            set_alpha_to_one=True,
            steps_offset=0,
            prediction_type="epsilon",
        )

    @property
    def description(self) -> str:
        """Short name of the inference sampler for reports, e.g. `DDPM-100`, `DDIM-10`."""
        return f"{self.sampler.upper()}-{self.num_inference_steps}"

    def noisy_batch(self, actions: torch.Tensor, generator: torch.Generator | None = None) -> NoisyBatch:
        """Noise a batch of clean actions to uniformly drawn steps.

        Args:
            actions: (B, H, A) normalized actions.
            generator: random source for the steps and the noise (on the actions' device).

        Returns:
            The noised actions, their steps and the noise.
        """
        noise = torch.randn(actions.shape, generator=generator, device=actions.device, dtype=actions.dtype)
        steps = torch.randint(
            0, self.num_train_steps, (actions.shape[0],), generator=generator, device=actions.device
        )  # (B,)
        noisy_actions = self.training_scheduler.add_noise(actions, noise, steps)  # (B, H, A)
        return NoisyBatch(noisy_actions, steps, noise)

    def training_loss(
        self,
        denoiser: Denoiser,
        actions: torch.Tensor,
        obs_features: torch.Tensor,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Mean-squared error between the added noise and the denoiser's prediction of it (scalar).

        Args:
            denoiser: the network being trained.
            actions: (B, H, A) normalized action chunks.
            obs_features: (B, To, Do) normalized observations.
            generator: random source for steps and noise.
        """
        batch = self.noisy_batch(actions, generator)
        return F.mse_loss(denoiser(batch.noisy_actions, batch.steps, obs_features), batch.noise)

    @torch.inference_mode()
    def sample(
        self,
        denoiser: Denoiser,
        obs_features: torch.Tensor,
        action_horizon: int,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Denoise one action chunk per observation, from Gaussian noise, in `num_inference_steps` calls.

        Args:
            denoiser: the trained network (in eval mode).
            obs_features: (B, To, Do) normalized observations.
            action_horizon: `H`.
            generator: random source of the initial noise (and of DDPM's per-step noise), on the observations'
                device; a seeded one makes the chunk reproducible.

        Returns:
            (B, H, A) normalized actions.
        """
        shape = (obs_features.shape[0], action_horizon, denoiser.action_dim)
        sample = torch.randn(shape, generator=generator, device=obs_features.device, dtype=obs_features.dtype)
        condition = denoiser.prepare(obs_features, self.steps, action_horizon)
        scheduler = self.inference_scheduler
        for index, step in enumerate(self._step_values):
            noise = denoiser.predict_noise(sample, condition, index)  # (B, H, A)
            sample = scheduler.step(noise, step, sample, generator=generator).prev_sample  # (B, H, A)
        return sample
