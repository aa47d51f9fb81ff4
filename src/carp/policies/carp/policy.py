"""The deployable CARP policy: normalizers, the frozen tokenizer and the coarse-to-fine transformer in one object.

`predict_action` maps raw observations to raw action chunks: normalize, predict the K scales of tokens, decode
f_hat, un-normalize. Rotation conversion (10-D -> 7-D) and choosing the executed slice `[To-1 : To-1+Ta]` stay with the
caller (`carp.evaluation`), so the policy is independent of the action space. A checkpoint is one self-contained file
(specs, weights, normalizer statistics, metadata) that loads strictly. It embeds the tokenizer artifact the policy was
trained with together with that artifact's sha256; loading recomputes the hash and refuses a tokenizer of the same
shape that is not the one the policy learned its tokens from.
"""

import functools
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from carp.config.image_encoder import ImageEncoderConfig
from carp.data.normalizer import MinMaxNormalizer
from carp.policies.base import POLICY_FORMAT_VERSION, Deployment, TimedPrediction
from carp.policies.carp.sampling import generate_chunk
from carp.policies.carp.spec import POLICY_TYPE, PolicySpec
from carp.policies.carp.trainer import compute_token_targets, teacher_forced_step
from carp.policies.carp.transformer import CoarseToFineTransformer
from carp.policies.checkpoint_files import read_policy
from carp.policies.wrapper import (
    TokenizedPolicy,
    check_policy_type,
    check_tokenizer_fit,
)
from carp.tokenizer.artifact import TokenizerArtifact
from carp.tokenizer.spec import TokenizerSpec

logger = logging.getLogger(__name__)

ONNX_BACKEND = "onnxruntime"


def check_specs_match(policy_spec: PolicySpec, tokenizer_spec: TokenizerSpec) -> None:
    """Raise ValueError unless the transformer was sized for this tokenizer (A, scales, C, V)."""
    pairs = {
        "action_dim": (policy_spec.action_dim, tokenizer_spec.action_dim),
        "scales": (policy_spec.scales, tokenizer_spec.scales),
        "latent_channels": (policy_spec.latent_channels, tokenizer_spec.latent_channels),
        "codebook_size": (policy_spec.codebook_size, tokenizer_spec.codebook_size),
    }
    check_tokenizer_fit(pairs, "policy", "policy spec does not match the tokenizer spec")


class CarpPolicy(TokenizedPolicy):
    """Normalizers + frozen tokenizer + coarse-to-fine transformer; a :class:`~carp.policies.base.Policy`.

    Args:
        tokenizer_artifact: the trained tokenizer with its training statistics and sha256; its tokenizer is frozen
            here (eval mode, no gradients) and becomes :attr:`tokenizer`.
        transformer: trained coarse-to-fine transformer.
        obs_normalizer: per-feature min-max statistics of the `Do` low-dim observation features.
        action_normalizer: per-feature min-max statistics of the `A` action dimensions of the policy's task (the
            task's own, also for a task the tokenizer was not trained on).
        metadata: plain values stored in the checkpoint (e.g. the tokenizer's registry reference, the task names).
        image_encoder: the camera encoder's settings for an image policy; None for a state policy.
    """

    policy_type = POLICY_TYPE

    def __init__(
        self,
        tokenizer_artifact: TokenizerArtifact,
        transformer: CoarseToFineTransformer,
        obs_normalizer: MinMaxNormalizer,
        action_normalizer: MinMaxNormalizer,
        metadata: dict[str, Any] | None = None,
        image_encoder: ImageEncoderConfig | None = None,
    ) -> None:
        check_specs_match(transformer.spec, tokenizer_artifact.tokenizer.spec)
        spec = transformer.spec
        super().__init__(
            tokenizer_artifact,
            transformer,
            obs_normalizer,
            action_normalizer,
            metadata,
            spec.obs_dim,
            image_encoder,
        )

    @property
    def spec(self) -> PolicySpec:
        """The transformer's spec."""
        return self.transformer.spec

    @property
    def model_calls_per_chunk(self) -> int:
        """`K`: one transformer call per scale."""
        return self.spec.num_scales

    def predict_action_timed(
        self,
        obs: np.ndarray | torch.Tensor,
        task_index: int | np.ndarray | torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        top_k: int | None = None,
        images: np.ndarray | torch.Tensor | None = None,
    ) -> TimedPrediction:
        """Predict raw action chunks and time prediction and decoding separately.

        Args:
            obs: (B, To, Do) raw low-dim observations (numpy or torch).
            task_index: see `PolicyModule.task_ids` (None: a multi-task policy's selected task).
            generator: random source for top-k sampling, on the policy's device.
            top_k: token choice of this call; None uses :meth:`configure_inference`'s (greedy by default). See
                `carp.policies.carp.sampling.select_tokens`.
            images: (B, To, cameras, 3, h, w) uint8 camera images of an image policy; None for a state policy.

        Returns:
            Actions (B, H, A) raw float32, the two durations in seconds and the K transformer calls.
        """
        top_k = self.top_k if top_k is None else top_k
        with torch.inference_mode():
            started = time.perf_counter()
            observations = self.observation_features(obs, self.spec.obs_steps, images, task_index)  # (B, To, F)
            encoded = time.perf_counter()
            chunk = generate_chunk(self.transformer, self.tokenizer, observations, top_k, generator)
            predicted = time.perf_counter()
            normalized_actions = self.tokenizer.decode_latent(chunk.latent)  # (B, H, A)
            actions = self.action_normalizer.unnormalize(normalized_actions).float().cpu().numpy()
            decoded = time.perf_counter()
        return TimedPrediction(
            actions, predicted - started, decoded - predicted, self.spec.num_scales, encoded - started
        )

    def training_loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Mean cross entropy of a teacher-forced forward pass over all L tokens (scalar float32).

        The frozen tokenizer encodes the batch's actions into the ground-truth ids and the teacher-forcing inputs
        (training tokenizes every window once instead, `carp.policies.carp.trainer`).

        Args:
            batch: `obs` (b, To, Do) and `actions` (b, H, A) normalized; `task_ids` (b,) long when multi-task;
                `images` (b, To, cameras, 3, h, w) uint8 for an image policy.
        """
        targets = compute_token_targets(self.tokenizer, batch["actions"])
        batch = batch | {
            "obs": self.batch_features(batch),
            "token_sequence": targets.token_sequence,
            "teacher_inputs": targets.teacher_inputs,
        }
        return teacher_forced_step(self.transformer, batch).loss

    def deployment(self, checkpoint_path: Path, backend: str, directory: Path) -> Deployment:
        """Workers run ONNX Runtime graphs exported into `directory` for `onnxruntime`, else this checkpoint in torch.

        The graphs bake in the current `top_k` and take state observations: an image policy runs in PyTorch, camera
        encoder included. An export failure is logged and falls back to PyTorch, which computes the same actions; the
        returned backend says which one runs.
        """
        if backend == ONNX_BACKEND and self.observation_encoder.kind == "state":
            from carp.policies.carp.onnx_policy import OnnxPolicy, export_policy_graphs

            try:
                export_policy_graphs(self, directory, self.top_k)
                return Deployment(ONNX_BACKEND, functools.partial(OnnxPolicy, Path(directory)))
            except Exception as error:  # an export problem must not cost the evaluation; PyTorch computes the same
                logger.warning(
                    "ONNX export of %s failed (%s: %s); evaluating with PyTorch",
                    checkpoint_path,
                    type(error).__name__,
                    error,
                )
        return super().deployment(checkpoint_path, backend, directory)

    def family_checkpoint(self) -> dict[str, Any]:
        """CARP's checkpoint entries: the spec, the transformer's weights and the tokenizer artifact with its sha256."""
        return {
            "policy_spec": self.spec.to_dict(),
            "transformer_state": self.transformer.state_dict(),
            **self.tokenizer_checkpoint(),
        }

    @classmethod
    def from_checkpoint(cls, checkpoint: dict[str, Any]) -> "CarpPolicy":
        """Rebuild a policy from :meth:`to_checkpoint` output, loading weights strictly.

        Raises:
            TokenizerMismatchError: the embedded tokenizer does not hash to the sha256 recorded with it.
            ValueError: another format version or policy type, or specs that do not fit together.
            KeyError, RuntimeError: an entry is missing, or weights do not fit their spec.
        """
        version = checkpoint.get("format_version") if isinstance(checkpoint, dict) else None
        if version != POLICY_FORMAT_VERSION:
            raise ValueError(
                f"policy checkpoint has format_version {version!r}, this code reads version {POLICY_FORMAT_VERSION}"
            )
        check_policy_type(checkpoint, POLICY_TYPE)
        transformer = CoarseToFineTransformer(PolicySpec.from_dict(checkpoint["policy_spec"]))
        transformer.load_state_dict(checkpoint["transformer_state"], strict=True)
        # The specs first: a tokenizer of another shape is named as such rather than as a hash difference.
        check_specs_match(transformer.spec, TokenizerSpec.from_dict(checkpoint["tokenizer"]["spec"]))
        return cls.with_checkpoint_parts(transformer, checkpoint)

    @classmethod
    def load(cls, path: Path, map_location: str | torch.device = "cpu") -> "CarpPolicy":
        """Read a CARP checkpoint written by :meth:`save` onto `map_location`.

        Raises:
            FileNotFoundError: no file at `path`.
            CheckpointError: as `carp.policies.registry.load_policy`, or the file holds another family.
        """
        return read_policy(Path(path), cls.from_checkpoint, map_location)
