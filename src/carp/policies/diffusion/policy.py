"""The deployable Diffusion Policy (DP-C or DP-T): normalizers, a denoiser and DP's sampler in one object.

`predict_action` maps raw observations to raw action chunks as the official policy does: normalize to [-1, 1],
denoise a Gaussian chunk in `num_inference_steps` denoiser calls (DDPM or DDIM, `carp.policies.diffusion.sampler`),
un-normalize. It runs in PyTorch under inference mode; the loop holds one denoiser call and one scheduler update per
step. Prediction time is the denoising loop; decoding time is the un-normalization (a diffusion policy has no decoder).
A checkpoint stores the family name, the family's config, the shapes, the weights (the EMA weights when the config
asks for them) and the normalizer statistics; it loads strictly.
"""

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import nn

from carp.config.image_encoder import ImageEncoderConfig
from carp.data.normalizer import MinMaxNormalizer
from carp.policies.base import TimedPrediction
from carp.policies.diffusion.config import SAMPLERS, DenoisingConfig
from carp.policies.diffusion.sampler import DiffusionSampler
from carp.policies.observations import checkpoint_image_encoder, restore_observation_encoder
from carp.policies.wrapper import PolicyModule, check_policy_type, checkpoint_normalizers

DenoiserFactory = Callable[[Any, int, int, int, int], nn.Module]
"""`factory(config, action_dim, feature_dim, obs_steps, action_horizon)` -> an untrained denoiser."""


class DiffusionPolicy(PolicyModule):
    """Normalizers + denoiser + sampler; a :class:`~carp.policies.base.Policy`.

    Args:
        policy_type: the registry name of the family (`diffusion_unet` or `diffusion_transformer`).
        config: the family's config (denoiser shape, training schedule, optimizer, EMA).
        denoiser: the noise-predicting network (`Denoiser` protocol of `carp.policies.diffusion.sampler`).
        obs_normalizer: min-max statistics of the `Do` low-dim observation features.
        action_normalizer: min-max statistics of the `A` action dimensions.
        action_horizon: `H`, actions per chunk.
        metadata: plain values stored in the checkpoint.
        image_encoder: the camera encoder's settings for an image policy; None for a state policy.
    """

    def __init__(
        self,
        policy_type: str,
        config: DenoisingConfig,
        denoiser: nn.Module,
        obs_normalizer: MinMaxNormalizer,
        action_normalizer: MinMaxNormalizer,
        action_horizon: int,
        metadata: dict[str, Any] | None = None,
        image_encoder: ImageEncoderConfig | None = None,
    ) -> None:
        super().__init__(
            obs_normalizer, action_normalizer, metadata, denoiser.obs_dim, denoiser.action_dim, image_encoder
        )
        self.policy_type = policy_type
        self.config = config
        self.denoiser = denoiser
        self.action_horizon = action_horizon
        # DP's protocol until `configure_inference` says otherwise.
        self.sampler = DiffusionSampler(config.num_train_steps, "ddpm", config.num_train_steps)

    def configure_inference(self, sampler: str = "ddpm", num_inference_steps: int | None = None) -> None:
        """Denoise later chunks with `sampler` (`ddpm` or `ddim`) in `num_inference_steps` calls (None: all)."""
        if sampler not in SAMPLERS:
            raise ValueError(f"sampler must be one of {SAMPLERS}, got {sampler!r}")
        steps = self.config.num_train_steps if num_inference_steps is None else num_inference_steps
        self.sampler = DiffusionSampler(self.config.num_train_steps, sampler, steps)

    @property
    def model_calls_per_chunk(self) -> int:
        """`N`, denoiser calls per chunk."""
        return self.sampler.num_inference_steps

    @property
    def description(self) -> str:
        """The sampler, e.g. `DDPM-100` or `DDIM-10`."""
        return self.sampler.description

    @property
    def draws_random(self) -> bool:
        """Always: every chunk starts from drawn noise (DDIM's later steps are deterministic, its start is not)."""
        return True

    def predict_action_timed(
        self,
        obs: np.ndarray | torch.Tensor,
        task_index: int | np.ndarray | torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        images: np.ndarray | torch.Tensor | None = None,
    ) -> TimedPrediction:
        """Denoise one raw action chunk per observation and time the loop and the un-normalization.

        Args:
            obs: (B, To, Do) raw low-dim observations.
            task_index: see `PolicyModule.task_ids` (None: a multi-task policy's selected task).
            generator: random source of the initial noise (and of DDPM's per-step noise); seeded per episode.
            images: (B, To, cameras, 3, h, w) uint8 camera images of an image policy; None for a state policy.

        Returns:
            Actions (B, H, A) raw float32, the two durations in seconds and the N denoiser calls.
        """
        with torch.inference_mode():
            started = time.perf_counter()
            denoiser = self.denoiser
            observations = self.observation_features(obs, denoiser.obs_steps, images, task_index)  # (B, To, F)
            encoded = time.perf_counter()
            normalized_actions = self.sampler.sample(denoiser, observations, self.action_horizon, generator)
            predicted = time.perf_counter()
            actions = self.action_normalizer.unnormalize(normalized_actions).float().cpu().numpy()  # (B, H, A)
            decoded = time.perf_counter()
        return TimedPrediction(
            actions, predicted - started, decoded - predicted, self.sampler.num_inference_steps, encoded - started
        )

    def training_loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """DP's loss: mean-squared error of the predicted noise at uniformly drawn diffusion steps (scalar).

        Args:
            batch: `obs` (b, To, Do) and `actions` (b, H, A) normalized; `images` (b, To, cameras, 3, h, w) uint8
                for an image policy; `task_ids` (b,) long for a multi-task policy.
        """
        return self.sampler.training_loss(self.denoiser, batch["actions"], self.batch_features(batch))

    def family_checkpoint(self) -> dict[str, Any]:
        """The diffusion entries: config, shapes and the denoiser's weights."""
        denoiser = self.denoiser
        return {
            "config": dataclasses.asdict(self.config),
            "shapes": {
                "action_dim": denoiser.action_dim,
                "obs_dim": denoiser.obs_dim,
                "obs_steps": denoiser.obs_steps,
                "action_horizon": self.action_horizon,
            },
            "denoiser_state": denoiser.state_dict(),
        }


def from_checkpoint(
    checkpoint: dict[str, Any], policy_type: str, config_class: type, make_denoiser: DenoiserFactory
) -> DiffusionPolicy:
    """Rebuild a policy from :meth:`DiffusionPolicy.to_checkpoint` output, loading the weights strictly."""
    check_policy_type(checkpoint, policy_type)
    config = config_class(**checkpoint["config"])
    shapes = checkpoint["shapes"]
    denoiser = make_denoiser(
        config, shapes["action_dim"], shapes["obs_dim"], shapes["obs_steps"], shapes["action_horizon"]
    )
    denoiser.load_state_dict(checkpoint["denoiser_state"], strict=True)
    obs_normalizer, action_normalizer = checkpoint_normalizers(checkpoint)
    policy = DiffusionPolicy(
        policy_type,
        config,
        denoiser,
        obs_normalizer,
        action_normalizer,
        shapes["action_horizon"],
        checkpoint["metadata"],
        checkpoint_image_encoder(checkpoint),
    )
    restore_observation_encoder(policy.observation_encoder, checkpoint)
    return policy.train(False)
