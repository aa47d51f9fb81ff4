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
from torch import nn

from carp.data.normalizer import MinMaxNormalizer
from carp.policies.base import (
    POLICY_FORMAT_VERSION,
    TORCH_BACKEND,
    Deployment,
    TimedPrediction,
    count_parameters,
)
from carp.policies.carp.sampling import check_top_k, generate_chunk
from carp.policies.carp.spec import PolicySpec
from carp.policies.carp.trainer import compute_token_targets, teacher_forced_step
from carp.policies.carp.transformer import CoarseToFineTransformer
from carp.tokenizer.artifact import TokenizerArtifact
from carp.tokenizer.spec import TokenizerSpec
from carp.training.checkpoint import CheckpointError, atomic_torch_save

logger = logging.getLogger(__name__)

POLICY_TYPE = "carp"
ONNX_BACKEND = "onnxruntime"


def check_specs_match(policy_spec: PolicySpec, tokenizer_spec: TokenizerSpec) -> None:
    """Raise ValueError unless the transformer was sized for this tokenizer (A, scales, C, V)."""
    pairs = {
        "action_dim": (policy_spec.action_dim, tokenizer_spec.action_dim),
        "scales": (policy_spec.scales, tokenizer_spec.scales),
        "latent_channels": (policy_spec.latent_channels, tokenizer_spec.latent_channels),
        "codebook_size": (policy_spec.codebook_size, tokenizer_spec.codebook_size),
    }
    mismatched = {name: values for name, values in pairs.items() if values[0] != values[1]}
    if mismatched:
        details = ", ".join(
            f"{name}: policy {ours} vs tokenizer {theirs}" for name, (ours, theirs) in mismatched.items()
        )
        raise ValueError(f"policy spec does not match the tokenizer spec ({details})")


class CarpPolicy(nn.Module):
    """Normalizers + frozen tokenizer + coarse-to-fine transformer; a :class:`~carp.policies.base.Policy`.

    Args:
        tokenizer_artifact: the trained tokenizer with its training statistics and sha256; its tokenizer is frozen
            here (eval mode, no gradients) and becomes :attr:`tokenizer`.
        transformer: trained coarse-to-fine transformer.
        obs_normalizer: per-feature min-max statistics of the `Do` observation features.
        action_normalizer: per-feature min-max statistics of the `A` action dimensions of the policy's task (the
            task's own, also for a task the tokenizer was not trained on).
        metadata: plain values stored in the checkpoint (e.g. the tokenizer's registry reference, the task names).
    """

    policy_type = POLICY_TYPE

    def __init__(
        self,
        tokenizer_artifact: TokenizerArtifact,
        transformer: CoarseToFineTransformer,
        obs_normalizer: MinMaxNormalizer,
        action_normalizer: MinMaxNormalizer,
        metadata: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        tokenizer = tokenizer_artifact.tokenizer
        check_specs_match(transformer.spec, tokenizer.spec)
        if obs_normalizer.num_features != transformer.spec.obs_dim:
            raise ValueError(
                f"obs normalizer has {obs_normalizer.num_features} features, the policy expects Do = "
                f"{transformer.spec.obs_dim}"
            )
        if action_normalizer.num_features != tokenizer.spec.action_dim:
            raise ValueError(
                f"action normalizer has {action_normalizer.num_features} features, the tokenizer has A = "
                f"{tokenizer.spec.action_dim}"
            )
        self.tokenizer = tokenizer.eval().requires_grad_(False)
        self.tokenizer_artifact = tokenizer_artifact
        self.transformer = transformer.eval()
        self.obs_normalizer = obs_normalizer
        self.action_normalizer = action_normalizer
        self.metadata = dict(metadata or {})
        self.top_k = 1

    @property
    def spec(self) -> PolicySpec:
        """The transformer's spec."""
        return self.transformer.spec

    @property
    def device(self) -> torch.device:
        """Device of the weights."""
        return self.transformer.position_embedding.device

    def train(self, mode: bool = True) -> "CarpPolicy":
        """Switch the transformer's mode; the tokenizer stays frozen in eval mode."""
        super().train(mode)
        self.tokenizer.eval()
        return self

    def _observations(self, obs: np.ndarray | torch.Tensor) -> torch.Tensor:
        spec = self.spec
        observations = torch.as_tensor(obs, dtype=torch.float32).to(self.device)
        if observations.dim() != 3 or tuple(observations.shape[1:]) != (spec.obs_steps, spec.obs_dim):
            raise ValueError(
                f"obs must have shape (B, To, Do) = (B, {spec.obs_steps}, {spec.obs_dim}), got "
                f"{tuple(observations.shape)}"
            )
        return self.obs_normalizer.normalize(observations)  # (B, To, Do)

    def _task_ids(self, task_index: int | np.ndarray | torch.Tensor | None, batch_size: int) -> torch.Tensor | None:
        if task_index is None:
            return None
        task_ids = torch.as_tensor(task_index, dtype=torch.long, device=self.device).reshape(-1)
        if task_ids.numel() == 1:
            task_ids = task_ids.expand(batch_size)
        if task_ids.numel() != batch_size:
            raise ValueError(f"task_index must be one index or one per sample ({batch_size}), got {task_ids.numel()}")
        if self.spec.num_tasks > 0 and not bool(((task_ids >= 0) & (task_ids < self.spec.num_tasks)).all()):
            raise ValueError(f"task indices must be in [0, {self.spec.num_tasks}), got {task_ids.tolist()}")
        return task_ids  # (B,)

    def configure_inference(self, top_k: int = 1) -> None:
        """Set the token choice of later predictions: 1 = greedy; k > 1 draws among the k most likely tokens."""
        check_top_k(top_k, self.spec.codebook_size)
        self.top_k = top_k

    @property
    def model_calls_per_chunk(self) -> int:
        """`K`: one transformer call per scale."""
        return self.spec.num_scales

    @property
    def num_parameters(self) -> int:
        """Parameters of the transformer (the frozen tokenizer is not counted)."""
        return count_parameters(self.transformer)

    @property
    def description(self) -> str:
        """`greedy` or `top-<k>`, the token choice of predictions."""
        return "greedy" if self.top_k == 1 else f"top-{self.top_k}"

    def predict_action_timed(
        self,
        obs: np.ndarray | torch.Tensor,
        task_index: int | np.ndarray | torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        top_k: int | None = None,
    ) -> TimedPrediction:
        """Predict raw action chunks and time prediction and decoding separately.

        Args:
            obs: (B, To, Do) raw observations (numpy or torch).
            task_index: None for single-task policies; otherwise one task index for the whole batch or (B,).
            generator: random source for top-k sampling, on the policy's device.
            top_k: token choice of this call; None uses :meth:`configure_inference`'s (greedy by default). See
                `carp.policies.carp.sampling.select_tokens`.

        Returns:
            Actions (B, H, A) raw float32, the two durations in seconds and the K transformer calls.
        """
        top_k = self.top_k if top_k is None else top_k
        with torch.inference_mode():
            started = time.perf_counter()
            observations = self._observations(obs)  # (B, To, Do)
            task_ids = self._task_ids(task_index, observations.shape[0])
            chunk = generate_chunk(self.transformer, self.tokenizer, observations, task_ids, top_k, generator)
            predicted = time.perf_counter()
            normalized_actions = self.tokenizer.decode_latent(chunk.latent)  # (B, H, A)
            actions = self.action_normalizer.unnormalize(normalized_actions).float().cpu().numpy()
            decoded = time.perf_counter()
        return TimedPrediction(actions, predicted - started, decoded - predicted, self.spec.num_scales)

    def predict_action(
        self,
        obs: np.ndarray | torch.Tensor,
        task_index: int | np.ndarray | torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        top_k: int | None = None,
    ) -> np.ndarray:
        """Predict raw action chunks (B, H, A) float32 from raw observations (B, To, Do).

        See :meth:`predict_action_timed` for the arguments.
        """
        return self.predict_action_timed(obs, task_index, generator, top_k).actions

    def training_loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Mean cross entropy of a teacher-forced forward pass over all L tokens (scalar float32).

        The frozen tokenizer encodes the batch's actions into the ground-truth ids and the teacher-forcing inputs
        (training tokenizes every window once instead, `carp.policies.carp.trainer`).

        Args:
            batch: `obs` (b, To, Do) and `actions` (b, H, A) normalized; `task_ids` (b,) long when multi-task.
        """
        targets = compute_token_targets(self.tokenizer, batch["actions"])
        batch = batch | {"token_sequence": targets.token_sequence, "teacher_inputs": targets.teacher_inputs}
        return teacher_forced_step(self.transformer, batch).loss

    def deployment(self, checkpoint_path: Path, backend: str, directory: Path) -> Deployment:
        """Workers run ONNX Runtime graphs exported into `directory` for `onnxruntime`, else this checkpoint in torch.

        The graphs bake in the current `top_k`. An export failure is logged and falls back to PyTorch, which
        computes the same actions; the returned backend says which one runs.
        """
        if backend == ONNX_BACKEND:
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
        from carp.policies.registry import load_policy

        return Deployment(TORCH_BACKEND, functools.partial(load_policy, Path(checkpoint_path)))

    def to_checkpoint(self) -> dict[str, Any]:
        """Self-contained state: spec, weights, the tokenizer artifact and its sha256, statistics, metadata."""
        return {
            "format_version": POLICY_FORMAT_VERSION,
            "policy_type": POLICY_TYPE,
            "policy_spec": self.spec.to_dict(),
            "transformer_state": self.transformer.state_dict(),
            "tokenizer": self.tokenizer_artifact.to_payload(),
            "tokenizer_sha256": self.tokenizer_artifact.sha256,
            "normalizers": {"obs": self.obs_normalizer.to_dict(), "action": self.action_normalizer.to_dict()},
            "metadata": self.metadata,
        }

    def save(self, path: Path) -> None:
        """Atomically write :meth:`to_checkpoint` to `path`."""
        atomic_torch_save(self.to_checkpoint(), Path(path))

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
        if checkpoint.get("policy_type") != POLICY_TYPE:
            raise ValueError(f"policy_type={checkpoint.get('policy_type')!r}: not a {POLICY_TYPE} checkpoint")
        transformer = CoarseToFineTransformer(PolicySpec.from_dict(checkpoint["policy_spec"]))
        transformer.load_state_dict(checkpoint["transformer_state"], strict=True)
        # The specs first: a tokenizer of another shape is named as such rather than as a hash difference.
        check_specs_match(transformer.spec, TokenizerSpec.from_dict(checkpoint["tokenizer"]["spec"]))
        tokenizer_artifact = TokenizerArtifact.from_payload(
            checkpoint["tokenizer"], checkpoint["tokenizer_sha256"], "the policy (the tokenizer it was trained with)"
        )
        normalizers = checkpoint["normalizers"]
        return cls(
            tokenizer_artifact,
            transformer,
            MinMaxNormalizer.from_dict(normalizers["obs"]),
            MinMaxNormalizer.from_dict(normalizers["action"]),
            checkpoint["metadata"],
        )

    @classmethod
    def load(cls, path: Path, map_location: str | torch.device = "cpu") -> "CarpPolicy":
        """Read a CARP checkpoint written by :meth:`save` onto `map_location` (through `load_policy`).

        Raises:
            FileNotFoundError: no file at `path`.
            CheckpointError: as `carp.policies.registry.load_policy`, or the file holds another family.
        """
        from carp.policies.registry import load_policy

        policy = load_policy(Path(path), map_location)
        if not isinstance(policy, cls):
            raise CheckpointError(f"{path}: holds a {policy.policy_type} policy, not a {POLICY_TYPE} one")
        return policy
