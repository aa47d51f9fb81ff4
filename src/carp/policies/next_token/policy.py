"""The deployable next-token policy: normalizers, the frozen registered tokenizer and the next-token transformer.

`predict_action` normalizes, predicts the L tokens of a chunk one per transformer call with a kv-cache
(`carp.policies.next_token.generation`), decodes them with the tokenizer and un-normalizes. It runs in PyTorch under
inference mode. Prediction time is the L-step generation; decoding time is the tokenizer's decoding plus the
un-normalization. Like CARP's, a checkpoint embeds the tokenizer artifact with its sha256, which loading checks.
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
from carp.policies.next_token.config import NextTokenConfig
from carp.policies.next_token.generation import check_tokenizer_matches, generate_tokens
from carp.policies.next_token.transformer import NextTokenTransformer
from carp.policies.wrapper import TokenizedPolicy, check_policy_type
from carp.tokenizer.artifact import TokenizerArtifact

POLICY_TYPE = "next_token"


class NextTokenPolicy(TokenizedPolicy):
    """Normalizers + frozen tokenizer + next-token transformer; a :class:`~carp.policies.base.Policy`.

    Args:
        tokenizer_artifact: the registered tokenizer the token ids come from; frozen here.
        transformer: the next-token transformer, sized for the tokenizer.
        obs_normalizer: min-max statistics of the `Do` low-dim observation features.
        action_normalizer: min-max statistics of the task's `A` action dimensions.
        metadata: plain values stored in the checkpoint.
        image_encoder: the camera encoder's settings for an image policy; None for a state policy.
    """

    policy_type = POLICY_TYPE

    def __init__(
        self,
        tokenizer_artifact: TokenizerArtifact,
        transformer: NextTokenTransformer,
        obs_normalizer: MinMaxNormalizer,
        action_normalizer: MinMaxNormalizer,
        metadata: dict[str, Any] | None = None,
        image_encoder: ImageEncoderConfig | None = None,
    ) -> None:
        check_tokenizer_matches(transformer, tokenizer_artifact.tokenizer)
        super().__init__(
            tokenizer_artifact,
            transformer,
            obs_normalizer,
            action_normalizer,
            metadata,
            transformer.obs_dim,
            image_encoder,
        )

    @property
    def model_calls_per_chunk(self) -> int:
        """`L`: one transformer call per token."""
        return self.transformer.sequence_length

    def predict_action_timed(
        self,
        obs: np.ndarray | torch.Tensor,
        task_index: int | np.ndarray | torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        images: np.ndarray | torch.Tensor | None = None,
    ) -> TimedPrediction:
        """Predict the L tokens one at a time, decode them, and time both parts.

        Args:
            obs: (B, To, Do) raw low-dim observations.
            task_index: see `PolicyModule.task_ids` (None: a multi-task policy's selected task).
            generator: random source of top-k draws, seeded per episode.
            images: (B, To, cameras, 3, h, w) uint8 camera images of an image policy; None for a state policy.

        Returns:
            Actions (B, H, A) raw float32, the two durations in seconds and the L transformer calls.
        """
        with torch.inference_mode():
            started = time.perf_counter()
            transformer = self.transformer
            features = self.observation_features(obs, transformer.obs_steps, images, task_index)  # (B, To, F)
            encoded = time.perf_counter()
            token_ids = generate_tokens(transformer, features, self.top_k, generator)  # (B, L)
            predicted = time.perf_counter()
            normalized_actions = self.tokenizer.decode_ids(self.tokenizer.sequence_to_ids(token_ids))  # (B, H, A)
            actions = self.action_normalizer.unnormalize(normalized_actions).float().cpu().numpy()
            decoded = time.perf_counter()
        return TimedPrediction(
            actions, predicted - started, decoded - predicted, transformer.sequence_length, encoded - started
        )

    def training_loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Mean cross entropy of the teacher-forced next-token logits over all L tokens (scalar float32).

        Args:
            batch: `obs` (b, To, Do) and `actions` (b, H, A) normalized; `task_ids` (b,) when multi-task; `images`
                (b, To, cameras, 3, h, w) uint8 for an image policy.
        """
        actions = batch["actions"]
        # The frozen tokenizer encodes in float32 whatever the loop's autocast: its ids must not depend on it.
        with torch.no_grad(), torch.autocast(actions.device.type, enabled=False):
            token_ids = self.tokenizer.ids_to_sequence(self.tokenizer.encode_to_ids(actions.float()))  # (b, L)
        logits = self.transformer(self.batch_features(batch), token_ids)  # (b, L, V)
        return F.cross_entropy(logits.flatten(0, 1).float(), token_ids.flatten())

    def family_checkpoint(self) -> dict[str, Any]:
        """The next-token entries: config, shapes, weights, the tokenizer artifact and its sha256."""
        transformer = self.transformer
        return {
            "config": dataclasses.asdict(transformer.config),
            "shapes": {
                "obs_dim": transformer.obs_dim,
                "obs_steps": transformer.obs_steps,
                "action_dim": transformer.action_dim,
                "scales": list(transformer.layout.scales),
                "codebook_size": transformer.codebook_size,
            },
            "transformer_state": transformer.state_dict(),
            **self.tokenizer_checkpoint(),
        }

    @classmethod
    def from_checkpoint(cls, checkpoint: dict[str, Any]) -> "NextTokenPolicy":
        """Rebuild a policy from :meth:`to_checkpoint` output; the tokenizer must hash to its recorded sha256.

        Raises:
            ValueError: another family's checkpoint, or a multi-task one of the earlier format, whose transformer
                embedded the task (`shapes.num_tasks` > 0; single-task ones recorded 0 and still load).
        """
        check_policy_type(checkpoint, POLICY_TYPE)
        shapes = checkpoint["shapes"]
        if shapes.get("num_tasks", 0) != 0:
            raise ValueError(
                "shapes.num_tasks > 0: a multi-task transformer of an earlier format, which this code no longer reads "
                "(the task embedding is the observation encoder's now); train it again"
            )
        transformer = NextTokenTransformer(
            NextTokenConfig(**checkpoint["config"]),
            shapes["obs_dim"],
            shapes["obs_steps"],
            shapes["action_dim"],
            tuple(shapes["scales"]),
            shapes["codebook_size"],
        )
        transformer.load_state_dict(checkpoint["transformer_state"], strict=True)
        return cls.with_checkpoint_parts(transformer, checkpoint)
