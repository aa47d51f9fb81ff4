"""The deployable VQ-BeT policy: normalizers, the frozen action VQ-VAE and the GPT with its two heads.

`predict_action` normalizes the observations, runs the GPT once, chooses one code per residual layer (drawn from
the code head's softmax with the caller's seeded generator, or the most likely one), decodes the codes with the
VQ-VAE, adds the offset head's offset of those codes and un-normalizes. Prediction time is the GPT, the code choice
and the offset; decoding time is the VQ-VAE decoding plus the un-normalization. The checkpoint holds the config,
the shapes and both networks' weights (the VQ-VAE's codebooks included), so it is self-contained.
"""

import dataclasses
import time
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from carp.config.image_encoder import ImageEncoderConfig
from carp.data.normalizer import MinMaxNormalizer
from carp.policies.base import TimedPrediction
from carp.policies.carp.sampling import gumbel_top_k, sampling_uniforms
from carp.policies.observations import checkpoint_image_encoder, restore_observation_encoder
from carp.policies.vq_bet.config import CODE_CHOICES, VqBetConfig
from carp.policies.vq_bet.transformer import BehaviorTransformer, code_losses
from carp.policies.wrapper import PolicyModule, check_policy_type, checkpoint_normalizers
from carp.tokenizer.kinds.chunk_vqvae import ActionAutoencoder, AutoencoderShape

POLICY_TYPE = "vq_bet"


def autoencoder_shape(config: VqBetConfig, action_horizon: int, action_dim: int) -> AutoencoderShape:
    """The VQ-VAE sizes `config` asks for, for chunks of (H, A) = (`action_horizon`, `action_dim`)."""
    return AutoencoderShape(
        action_horizon,
        action_dim,
        config.encoder_hidden_width,
        config.latent_width,
        config.num_residual_layers,
        config.num_codes,
        config.codebook_decay,
    )


class VqBetPolicy(PolicyModule):
    """Normalizers + frozen VQ-VAE + GPT with code and offset heads; a :class:`~carp.policies.base.Policy`.

    Args:
        autoencoder: the trained action VQ-VAE; frozen here (eval mode, no gradients).
        transformer: the GPT with its heads, sized for the same codes, layers and chunk.
        obs_normalizer: min-max statistics of the `Do` low-dim observation features.
        action_normalizer: min-max statistics of the task's `A` action dimensions.
        metadata: plain values stored in the checkpoint.
        image_encoder: the camera encoder's settings for an image policy; None for a state policy.

    Raises:
        ValueError: the VQ-VAE and the transformer disagree on the chunk, codes or layers.
    """

    policy_type = POLICY_TYPE

    def __init__(
        self,
        autoencoder: ActionAutoencoder,
        transformer: BehaviorTransformer,
        obs_normalizer: MinMaxNormalizer,
        action_normalizer: MinMaxNormalizer,
        metadata: dict[str, Any] | None = None,
        image_encoder: ImageEncoderConfig | None = None,
    ) -> None:
        expected = autoencoder_shape(transformer.config, transformer.action_horizon, transformer.action_dim)
        if autoencoder.shape != expected:
            raise ValueError(f"VQ-VAE shape {autoencoder.shape} does not match the transformer's {expected}")
        super().__init__(
            obs_normalizer, action_normalizer, metadata, transformer.obs_dim, transformer.action_dim, image_encoder
        )
        self.autoencoder = autoencoder.eval().requires_grad_(False)
        self.transformer = transformer.eval()
        self.code_choice = "sample"
        self.freeze_after_steps: int | None = None
        # Optimizer steps taken in training; persisted in the training state (not in the policy checkpoint) so that a
        # resumed run freezes the GPT at the same step.
        self.register_buffer("trained_steps", torch.zeros((), dtype=torch.long))

    def train(self, mode: bool = True) -> "VqBetPolicy":
        """Switch the transformer's mode; the VQ-VAE stays frozen in eval mode."""
        super().train(mode)
        self.autoencoder.eval()
        return self

    def configure_inference(self, code_choice: str = "sample") -> None:
        """Code choice of later predictions: `sample` (seeded draws from the code head's softmax) or `greedy`."""
        if code_choice not in CODE_CHOICES:
            raise ValueError(f"code_choice must be one of {CODE_CHOICES}, got {code_choice!r}")
        self.code_choice = code_choice

    @property
    def description(self) -> str:
        """`sampled` or `greedy`, the code choice of predictions."""
        return "sampled" if self.code_choice == "sample" else "greedy"

    @property
    def draws_random(self) -> bool:
        """Sampled code choice draws; greedy does not."""
        return self.code_choice == "sample"

    @property
    def model_calls_per_chunk(self) -> int:
        """One GPT call per chunk."""
        return 1

    def choose_codes(self, logits: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        """(B, layers, codes) logits -> (B, layers) long codes, drawn from their softmax or greedy."""
        if self.code_choice == "greedy":
            return logits.argmax(dim=-1)
        batch, layers, codes = logits.shape
        # Gumbel-max over all codes is a draw from the softmax, with the uniforms of the other families' sampling.
        return gumbel_top_k(logits, sampling_uniforms(batch, layers, codes, generator, logits.device))

    def predict_action_timed(
        self,
        obs: np.ndarray | torch.Tensor,
        task_index: int | np.ndarray | torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        images: np.ndarray | torch.Tensor | None = None,
    ) -> TimedPrediction:
        """Run the GPT once, choose the codes, add their offset, decode, and time the parts.

        Args:
            obs: (B, To, Do) raw low-dim observations.
            task_index: see `PolicyModule.task_ids` (None: a multi-task policy's selected task).
            generator: random source of the code draws, seeded per episode; unused when greedy.
            images: (B, To, cameras, 3, h, w) uint8 camera images of an image policy; None for a state policy.

        Returns:
            Actions (B, H, A) raw float32, the durations in seconds and one model call.
        """
        with torch.inference_mode():
            started = time.perf_counter()
            transformer = self.transformer
            obs_features = self.observation_features(obs, transformer.obs_steps, images, task_index)  # (B, To, F)
            encoded = time.perf_counter()
            features = transformer.features(obs_features)  # (B, output_width)
            code_ids = self.choose_codes(transformer.code_logits(features).float(), generator)  # (B, layers)
            offsets = transformer.code_offsets(features, code_ids)  # (B, H, A)
            predicted = time.perf_counter()
            normalized_actions = self.autoencoder.decode_ids(code_ids) + offsets  # (B, H, A)
            actions = self.action_normalizer.unnormalize(normalized_actions).float().cpu().numpy()
            decoded = time.perf_counter()
        return TimedPrediction(actions, predicted - started, decoded - predicted, 1, encoded - started)

    def is_frozen(self) -> bool:
        """Whether the freeze schedule has stopped the GPT and the code head (training mode only)."""
        return self.freeze_after_steps is not None and int(self.trained_steps) >= self.freeze_after_steps

    def training_loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Weighted focal losses of the codes plus the weighted L1 of the offset-corrected decoding (scalar float32).

        The target codes are the frozen VQ-VAE's codes of the batch's chunks; the offset is read at those codes and
        added to their decoding, so the offset head learns what the codes miss. Once :meth:`is_frozen`, the GPT and
        the code head run without gradients and only the offset head trains (VQ-BeT's schedule); every call in
        training mode counts one step.

        Args:
            batch: `obs` (b, To, Do) and `actions` (b, H, A) normalized; `images` (b, To, cameras, 3, h, w) uint8 for
                an image policy.
        """
        config = self.transformer.config
        actions = batch["actions"]
        # The frozen VQ-VAE codes in float32 whatever the loop's autocast: targets must not depend on it.
        with torch.no_grad(), torch.autocast(actions.device.type, enabled=False):
            code_ids = self.autoencoder.encode_to_ids(actions.float())  # (b, layers)
            decoded = self.autoencoder.decode_ids(code_ids)  # (b, H, A)
        frozen = self.training and self.is_frozen()
        if self.training:
            self.trained_steps += 1
        with torch.set_grad_enabled(torch.is_grad_enabled() and not frozen):
            features = self.transformer.features(self.batch_features(batch))  # (b, output_width)
            logits = self.transformer.code_logits(features)  # (b, layers, codes)
        primary, secondary = code_losses(logits, code_ids, config.focal_gamma)
        offsets = self.transformer.code_offsets(features, code_ids).float()  # (b, H, A)
        offset_loss = F.l1_loss(decoded + offsets, actions.float())
        return (
            config.primary_code_weight * primary
            + config.secondary_code_weight * secondary
            + config.offset_weight * offset_loss
        )

    def family_checkpoint(self) -> dict[str, Any]:
        """The VQ-BeT entries: config, shapes, the transformer's and the VQ-VAE's weights."""
        transformer = self.transformer
        return {
            "config": dataclasses.asdict(transformer.config),
            "shapes": {
                "obs_dim": transformer.obs_dim,
                "obs_steps": transformer.obs_steps,
                "action_horizon": transformer.action_horizon,
                "action_dim": transformer.action_dim,
            },
            "transformer_state": transformer.state_dict(),
            "autoencoder_state": self.autoencoder.state_dict(),
        }

    @classmethod
    def from_checkpoint(cls, checkpoint: dict[str, Any]) -> "VqBetPolicy":
        """Rebuild a policy from :meth:`to_checkpoint` output, loading every weight strictly."""
        check_policy_type(checkpoint, POLICY_TYPE)
        config = VqBetConfig(**checkpoint["config"])
        shapes = checkpoint["shapes"]
        transformer = BehaviorTransformer(
            config, shapes["obs_dim"], shapes["obs_steps"], shapes["action_horizon"], shapes["action_dim"]
        )
        transformer.load_state_dict(checkpoint["transformer_state"], strict=True)
        autoencoder = ActionAutoencoder(autoencoder_shape(config, shapes["action_horizon"], shapes["action_dim"]))
        autoencoder.load_state_dict(checkpoint["autoencoder_state"], strict=True)
        policy = cls(
            autoencoder,
            transformer,
            *checkpoint_normalizers(checkpoint),
            checkpoint["metadata"],
            checkpoint_image_encoder(checkpoint),
        )
        restore_observation_encoder(policy.observation_encoder, checkpoint)
        return policy
