"""The EDM teacher's and the consistency student's deployable policies: normalizers, DP-C's U-Net and a sampler.

Both wrap the one U-Net of `carp.policies.diffusion.unet` with the EDM preconditioning of
`carp.policies.consistency.karras`; the teacher reads one noise level, the student two (where it is and where it
jumps to). `predict_action` normalizes observations, samples a normalized chunk (the teacher by Heun steps through
the probability-flow ODE, the student in one jump or a short chain of jumps), clamps it to [-1, 1] as the official
code does at inference, and un-normalizes it. A checkpoint stores the family name, its config, the noise schedule,
the shapes, the U-Net's weights (the EMA weights when the config asks for them) and the normalizer statistics.
"""

import abc
import dataclasses
import time
from typing import Any

import numpy as np
import torch

from carp.config.image_encoder import ImageEncoderConfig
from carp.data.normalizer import MinMaxNormalizer
from carp.policies.base import TimedPrediction
from carp.policies.consistency.config import STUDENT, TEACHER, ConsistencyConfig, EDMConfig
from carp.policies.consistency.karras import KarrasSchedule, expand_like, heun_sample, pseudo_huber
from carp.policies.diffusion.unet import ConditionalUNet1D
from carp.policies.observations import checkpoint_image_encoder, restore_observation_encoder
from carp.policies.wrapper import PolicyModule, check_policy_type, checkpoint_normalizers

CLIP_RANGE = 1.0
"""Normalized actions lie in [-1, 1]; samples are clamped to that range at inference."""


def schedule_of(config: EDMConfig) -> KarrasSchedule:
    """The teacher config's noise-level range and preconditioning constants."""
    return KarrasSchedule(config.sigma_min, config.sigma_max, config.rho, config.sigma_data)


class KarrasPolicy(PolicyModule):
    """What the teacher and the student share: normalizers, the U-Net, the schedule, timing and checkpoints.

    Args:
        config: the family's params section.
        unet: DP-C's U-Net with one (teacher) or two (student) noise-level inputs.
        schedule: noise levels and preconditioning (the teacher's).
        obs_normalizer: min-max statistics of the `Do` low-dim observation features.
        action_normalizer: min-max statistics of the `A` action dimensions.
        action_horizon: `H`.
        metadata: plain values stored in the checkpoint.
        image_encoder: the camera encoder's settings for an image policy; None for a state policy.
    """

    def __init__(
        self,
        config: Any,
        unet: ConditionalUNet1D,
        schedule: KarrasSchedule,
        obs_normalizer: MinMaxNormalizer,
        action_normalizer: MinMaxNormalizer,
        action_horizon: int,
        metadata: dict[str, Any] | None = None,
        image_encoder: ImageEncoderConfig | None = None,
    ) -> None:
        super().__init__(obs_normalizer, action_normalizer, metadata, unet.obs_dim, unet.action_dim, image_encoder)
        self.config = config
        self.unet = unet
        self.schedule = schedule
        self.action_horizon = action_horizon

    def _network(self, unet: ConditionalUNet1D, noisy: torch.Tensor, sigmas: list[torch.Tensor], features):
        """F(c_in(sigma) x, c_noise of each level) for levels `sigmas` ((B,) each; the first sets c_in)."""
        c_in = self.schedule.preconditioning(sigmas[0]).c_in
        noise_inputs = torch.stack([self.schedule.preconditioning(sigma).c_noise for sigma in sigmas], dim=1)
        return unet(noisy * expand_like(c_in, noisy), noise_inputs.squeeze(1), features)  # (B, H, A)

    @abc.abstractmethod
    def sample(self, features: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        """(B, H, A) normalized chunks given (B, To, F) features."""

    def predict_action_timed(
        self,
        obs: np.ndarray | torch.Tensor,
        task_index: int | np.ndarray | torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        images: np.ndarray | torch.Tensor | None = None,
    ) -> TimedPrediction:
        """Sample one raw action chunk per observation and time the sampling and the un-normalization.

        Args:
            obs: (B, To, Do) raw low-dim observations.
            task_index: must be None (single-task families).
            generator: random source of the noise; seeded per episode.
            images: (B, To, cameras, 3, h, w) uint8 camera images of an image policy; None for a state policy.

        Returns:
            Actions (B, H, A) raw float32, the durations in seconds and the U-Net calls.
        """
        if task_index is not None:
            raise ValueError(f"a {self.policy_type} policy is single-task; got a task index")
        with torch.inference_mode():
            started = time.perf_counter()
            features = self.observation_features(obs, self.unet.obs_steps, images)  # (B, To, F)
            encoded = time.perf_counter()
            normalized_actions = self.sample(features, generator).clamp(-CLIP_RANGE, CLIP_RANGE)  # (B, H, A)
            predicted = time.perf_counter()
            actions = self.action_normalizer.unnormalize(normalized_actions).float().cpu().numpy()
            decoded = time.perf_counter()
        return TimedPrediction(
            actions, predicted - started, decoded - predicted, self.model_calls_per_chunk, encoded - started
        )

    def initial_noise(self, features: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        """(B, H, A) Gaussian chunks at sigma_max."""
        shape = (features.shape[0], self.action_horizon, self.unet.action_dim)
        return self.schedule.initial_noise(shape, generator, features.device, features.dtype)

    def family_checkpoint(self) -> dict[str, Any]:
        """Config, schedule, shapes and the U-Net's weights."""
        unet = self.unet
        return {
            "config": dataclasses.asdict(self.config),
            "schedule": dataclasses.asdict(self.schedule),
            "shapes": {
                "action_dim": unet.action_dim,
                "obs_dim": unet.obs_dim,
                "obs_steps": unet.obs_steps,
                "action_horizon": self.action_horizon,
            },
            "unet_state": unet.state_dict(),
        }

    @classmethod
    def from_checkpoint(cls, checkpoint: dict[str, Any]) -> "KarrasPolicy":
        """Rebuild a policy from :meth:`to_checkpoint` output, loading the weights strictly."""
        check_policy_type(checkpoint, cls.policy_type)
        config = cls.config_class(**checkpoint["config"])
        shapes = checkpoint["shapes"]
        unet = ConditionalUNet1D(
            config, shapes["action_dim"], shapes["obs_dim"], shapes["obs_steps"], cls.num_noise_inputs
        )
        unet.load_state_dict(checkpoint["unet_state"], strict=True)
        policy = cls(
            config,
            unet,
            KarrasSchedule(**checkpoint["schedule"]),
            *checkpoint_normalizers(checkpoint),
            shapes["action_horizon"],
            checkpoint["metadata"],
            checkpoint_image_encoder(checkpoint),
        )
        restore_observation_encoder(policy.observation_encoder, checkpoint)
        return policy.train(False)


class EDMPolicy(KarrasPolicy):
    """The teacher: an EDM denoiser sampled by Heun's method; a :class:`~carp.policies.base.Policy`."""

    policy_type = TEACHER
    config_class = EDMConfig
    num_noise_inputs = 1

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.num_levels = 80

    def configure_inference(self, num_levels: int = 80) -> None:
        """Sample later chunks through `num_levels` noise levels (2 * (num_levels - 1) U-Net calls)."""
        if num_levels < 2:
            raise ValueError(f"num_levels must be >= 2, got {num_levels}")
        self.num_levels = num_levels

    @property
    def model_calls_per_chunk(self) -> int:
        """Two U-Net calls per Heun step."""
        return 2 * (self.num_levels - 1)

    @property
    def description(self) -> str:
        """E.g. `Heun-80`."""
        return f"Heun-{self.num_levels}"

    def denoise(self, noisy: torch.Tensor, sigma: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """D(x, sigma): the denoised estimate (B, H, A) of noisy chunks (B, H, A) at levels sigma (B,)."""
        scalings = self.schedule.preconditioning(sigma)
        output = self._network(self.unet, noisy, [sigma], features)
        return expand_like(scalings.c_skip, noisy) * noisy + expand_like(scalings.c_out, noisy) * output

    def sample(self, features: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        """Heun steps from sigma_max to sigma_min, each denoised estimate clamped to [-1, 1] (the official sampler)."""
        sigmas = self.schedule.discretization(self.num_levels).to(features.device)

        def clamped(noisy: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
            return self.denoise(noisy, sigma, features).clamp(-CLIP_RANGE, CLIP_RANGE)

        return heun_sample(clamped, self.initial_noise(features, generator), sigmas)

    def training_loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """EDM's loss (scalar): the lambda(sigma)-weighted pseudo-Huber error of D(x_0 + sigma noise, sigma).

        The target is x_0; the noise levels are log-normal.

        Args:
            batch: `obs` (b, To, Do) and `actions` (b, H, A) normalized; `images` for an image policy.
        """
        actions = batch["actions"]
        sigma = self.schedule.log_normal_levels(
            actions.shape[0], self.config.log_sigma_mean, self.config.log_sigma_std, None, actions.device
        )  # (b,)
        noisy = actions + expand_like(sigma, actions) * torch.randn_like(actions)
        denoised = self.denoise(noisy, sigma, self.batch_features(batch))
        return pseudo_huber(denoised, actions, self.schedule.loss_weight(sigma))


class ConsistencyPolicy(KarrasPolicy):
    """The student G(x, t, s), a jump from level t to level s along the teacher's ODE; a `Policy`.

    ``G(x, t, s) = (s / t) x + (1 - s / t) g(x, t, s)``, where g is the preconditioned U-Net read at both levels
    (CTM's parameterization, as the official `CTM_calc_out`). One-step sampling jumps from sigma_max to sigma_min;
    chained sampling re-noises the result to each level of `chain_levels` and jumps to sigma_min again.
    """

    policy_type = STUDENT
    config_class = ConsistencyConfig
    num_noise_inputs = 2

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.chain_levels: tuple[int, ...] = ()
        # Attached by the family's training (`carp.policies.consistency.distillation`); never saved with the policy.
        self.distillation: torch.nn.Module | None = None

    def configure_inference(self, chain_levels: tuple[int, ...] | list[int] = ()) -> None:
        """Chain later samples through these positions of the `num_levels` discretization ([]: one step)."""
        chain_levels = tuple(chain_levels)
        if any(not 1 <= position < self.config.num_levels for position in chain_levels) or any(
            a >= b for a, b in zip(chain_levels, chain_levels[1:])
        ):
            raise ValueError(
                f"chain_levels must be strictly increasing positions in [1, {self.config.num_levels}), "
                f"got {list(chain_levels)}"
            )
        self.chain_levels = chain_levels

    @property
    def model_calls_per_chunk(self) -> int:
        """One U-Net call per jump."""
        return 1 + len(self.chain_levels)

    @property
    def description(self) -> str:
        """`1-step` or e.g. `3-step`."""
        return f"{self.model_calls_per_chunk}-step"

    def denoise(
        self,
        noisy: torch.Tensor,
        sigma: torch.Tensor,
        target_sigma: torch.Tensor,
        features: torch.Tensor,
        unet: ConditionalUNet1D | None = None,
    ) -> torch.Tensor:
        """g(x, t, s) (B, H, A): the preconditioned U-Net's estimate of the clean chunk; see :meth:`jump`."""
        scalings = self.schedule.preconditioning(sigma)
        output = self._network(unet or self.unet, noisy, [sigma, target_sigma], features)
        return expand_like(scalings.c_skip, noisy) * noisy + expand_like(scalings.c_out, noisy) * output

    def jump(
        self,
        noisy: torch.Tensor,
        sigma: torch.Tensor,
        target_sigma: torch.Tensor,
        features: torch.Tensor,
        unet: ConditionalUNet1D | None = None,
    ) -> torch.Tensor:
        """G(x, t, s): chunks (B, H, A) at levels t = `sigma` (B,) moved to levels s = `target_sigma` (B,).

        Args:
            noisy: (B, H, A).
            sigma: (B,) current levels.
            target_sigma: (B,) levels to jump to, at most `sigma`.
            features: (B, To, F) observation features.
            unet: the network to read (the distillation's target network); None reads the student's own.
        """
        denoised = self.denoise(noisy, sigma, target_sigma, features, unet)
        ratio = expand_like(target_sigma / sigma, noisy)
        return ratio * noisy + (1 - ratio) * denoised

    def sample(self, features: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        """One jump from sigma_max to sigma_min, then one re-noise and jump per chain level."""
        batch = features.shape[0]
        schedule = self.schedule
        floor = torch.full((batch,), schedule.sigma_min, device=features.device)
        top = torch.full((batch,), schedule.sigma_max, device=features.device)
        sample = self.jump(self.initial_noise(features, generator), top, floor, features).clamp(-CLIP_RANGE, CLIP_RANGE)
        for position in self.chain_levels:
            sigma = schedule.levels(torch.tensor(position), self.config.num_levels).to(features.device).expand(batch)
            noise = torch.randn(sample.shape, generator=generator, device=sample.device, dtype=sample.dtype)
            noisy = sample + expand_like(sigma, sample) * noise
            sample = self.jump(noisy, sigma, floor, features).clamp(-CLIP_RANGE, CLIP_RANGE)
        return sample

    def training_loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """The weighted sum of the consistency-trajectory and denoising losses (scalar).

        Needs the distillation attached by the family's training (its teacher and target network).
        """
        if self.distillation is None:
            raise RuntimeError("a consistency_policy trains by distillation from its teacher; none is attached")
        losses = self.distillation(self, batch)
        return losses.total(self.config.trajectory_weight, self.config.denoising_weight)
