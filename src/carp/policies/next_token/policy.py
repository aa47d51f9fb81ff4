"""The deployable next-token policy: normalizers, the frozen registered tokenizer and the next-token transformer.

`predict_action` normalizes, predicts the L tokens of a chunk one per transformer call with a kv-cache
(`carp.policies.next_token.generation`), decodes them with the tokenizer and un-normalizes. It runs in PyTorch under
inference mode. Prediction time is the L-step generation; decoding time is the tokenizer's decoding plus the
un-normalization. Like CARP's, a checkpoint embeds the tokenizer artifact with its sha256, which loading checks.
"""

import dataclasses
import functools
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from carp.data.normalizer import MinMaxNormalizer
from carp.policies.base import POLICY_FORMAT_VERSION, TORCH_BACKEND, Deployment, TimedPrediction, count_parameters
from carp.policies.carp.sampling import check_top_k
from carp.policies.next_token.config import NextTokenConfig
from carp.policies.next_token.generation import check_tokenizer_matches, generate_tokens
from carp.policies.next_token.transformer import NextTokenTransformer
from carp.tokenizer.artifact import TokenizerArtifact
from carp.training.checkpoint import atomic_torch_save

POLICY_TYPE = "next_token"


class NextTokenPolicy(nn.Module):
    """Normalizers + frozen tokenizer + next-token transformer; a :class:`~carp.policies.base.Policy`.

    Args:
        tokenizer_artifact: the registered tokenizer the token ids come from; frozen here.
        transformer: the next-token transformer, sized for the tokenizer.
        obs_normalizer: min-max statistics of the `Do` observation features.
        action_normalizer: min-max statistics of the task's `A` action dimensions.
        metadata: plain values stored in the checkpoint.
    """

    policy_type = POLICY_TYPE

    def __init__(
        self,
        tokenizer_artifact: TokenizerArtifact,
        transformer: NextTokenTransformer,
        obs_normalizer: MinMaxNormalizer,
        action_normalizer: MinMaxNormalizer,
        metadata: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        tokenizer = tokenizer_artifact.tokenizer
        check_tokenizer_matches(transformer, tokenizer)
        if obs_normalizer.num_features != transformer.obs_dim:
            raise ValueError(
                f"obs normalizer has {obs_normalizer.num_features} features, the policy expects Do = "
                f"{transformer.obs_dim}"
            )
        self.tokenizer = tokenizer.eval().requires_grad_(False)
        self.tokenizer_artifact = tokenizer_artifact
        self.transformer = transformer.eval()
        self.obs_normalizer = obs_normalizer
        self.action_normalizer = action_normalizer
        self.metadata = dict(metadata or {})
        self.top_k = 1

    def train(self, mode: bool = True) -> "NextTokenPolicy":
        """Switch the transformer's mode; the tokenizer stays frozen in eval mode."""
        super().train(mode)
        self.tokenizer.eval()
        return self

    def configure_inference(self, top_k: int = 1) -> None:
        """Token choice of later predictions: 1 = greedy; k > 1 draws among the k most likely tokens."""
        check_top_k(top_k, self.transformer.codebook_size)
        self.top_k = top_k

    @property
    def model_calls_per_chunk(self) -> int:
        """`L`: one transformer call per token."""
        return self.transformer.sequence_length

    @property
    def num_parameters(self) -> int:
        """Parameters of the transformer (the frozen tokenizer is not counted)."""
        return count_parameters(self.transformer)

    @property
    def description(self) -> str:
        """`greedy` or `top-<k>`."""
        return "greedy" if self.top_k == 1 else f"top-{self.top_k}"

    @property
    def device(self) -> torch.device:
        """Device of the weights."""
        return self.transformer.position_embedding.device

    def _task_ids(self, task_index: Any, batch_size: int) -> torch.Tensor | None:
        if task_index is None:
            return None
        task_ids = torch.as_tensor(task_index, dtype=torch.long, device=self.device).reshape(-1)
        return task_ids.expand(batch_size) if task_ids.numel() == 1 else task_ids  # (B,)

    def predict_action_timed(
        self,
        obs: np.ndarray | torch.Tensor,
        task_index: int | np.ndarray | torch.Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> TimedPrediction:
        """Predict the L tokens one at a time, decode them, and time both parts.

        Args:
            obs: (B, To, Do) raw observations.
            task_index: None for single-task policies; one index or (B,) otherwise.
            generator: random source of top-k draws, seeded per episode.

        Returns:
            Actions (B, H, A) raw float32, the two durations in seconds and the L transformer calls.
        """
        with torch.inference_mode():
            started = time.perf_counter()
            observations = torch.as_tensor(obs, dtype=torch.float32).to(self.device)
            expected = (self.transformer.obs_steps, self.transformer.obs_dim)
            if observations.dim() != 3 or tuple(observations.shape[1:]) != expected:
                raise ValueError(f"obs must have shape (B, To, Do) = (B, {expected[0]}, {expected[1]}), got "
                                 f"{tuple(observations.shape)}")  # fmt: skip
            normalized = self.obs_normalizer.normalize(observations)  # (B, To, Do)
            task_ids = self._task_ids(task_index, normalized.shape[0])
            token_ids = generate_tokens(self.transformer, normalized, task_ids, self.top_k, generator)  # (B, L)
            predicted = time.perf_counter()
            normalized_actions = self.tokenizer.decode_ids(self.tokenizer.sequence_to_ids(token_ids))  # (B, H, A)
            actions = self.action_normalizer.unnormalize(normalized_actions).float().cpu().numpy()
            decoded = time.perf_counter()
        return TimedPrediction(actions, predicted - started, decoded - predicted, self.transformer.sequence_length)

    def predict_action(
        self,
        obs: np.ndarray | torch.Tensor,
        task_index: int | np.ndarray | torch.Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> np.ndarray:
        """(B, H, A) float32 raw actions; see :meth:`predict_action_timed`."""
        return self.predict_action_timed(obs, task_index, generator).actions

    def training_loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Mean cross entropy of the teacher-forced next-token logits over all L tokens (scalar float32).

        Args:
            batch: `obs` (b, To, Do) and `actions` (b, H, A) normalized; `task_ids` (b,) when multi-task.
        """
        actions = batch["actions"]
        # The frozen tokenizer encodes in float32 whatever the loop's autocast: its ids must not depend on it.
        with torch.no_grad(), torch.autocast(actions.device.type, enabled=False):
            token_ids = self.tokenizer.ids_to_sequence(self.tokenizer.encode_to_ids(actions.float()))  # (b, L)
        logits = self.transformer(batch["obs"], token_ids, batch.get("task_ids"))  # (b, L, V)
        return F.cross_entropy(logits.flatten(0, 1).float(), token_ids.flatten())

    def deployment(self, checkpoint_path: Path, backend: str, directory: Path) -> Deployment:
        """Always PyTorch with the kv-cache, whatever `backend` asks: the report names the backend that ran."""
        from carp.policies.registry import load_policy

        return Deployment(TORCH_BACKEND, functools.partial(load_policy, Path(checkpoint_path)))

    def to_checkpoint(self) -> dict[str, Any]:
        """Self-contained state: config, shapes, weights, the tokenizer artifact and its sha256, statistics."""
        transformer = self.transformer
        return {
            "format_version": POLICY_FORMAT_VERSION,
            "policy_type": POLICY_TYPE,
            "config": dataclasses.asdict(transformer.config),
            "shapes": {
                "obs_dim": transformer.obs_dim,
                "obs_steps": transformer.obs_steps,
                "action_dim": transformer.action_dim,
                "scales": list(transformer.layout.scales),
                "codebook_size": transformer.codebook_size,
                "num_tasks": transformer.num_tasks,
            },
            "transformer_state": transformer.state_dict(),
            "tokenizer": self.tokenizer_artifact.to_payload(),
            "tokenizer_sha256": self.tokenizer_artifact.sha256,
            "normalizers": {"obs": self.obs_normalizer.to_dict(), "action": self.action_normalizer.to_dict()},
            "metadata": self.metadata,
        }

    def save(self, path: Path) -> None:
        """Atomically write :meth:`to_checkpoint` to `path`."""
        atomic_torch_save(self.to_checkpoint(), Path(path))

    @classmethod
    def from_checkpoint(cls, checkpoint: dict[str, Any]) -> "NextTokenPolicy":
        """Rebuild a policy from :meth:`to_checkpoint` output; the tokenizer must hash to its recorded sha256."""
        if checkpoint.get("policy_type") != POLICY_TYPE:
            raise ValueError(f"policy_type={checkpoint.get('policy_type')!r}: not a {POLICY_TYPE} checkpoint")
        shapes = checkpoint["shapes"]
        transformer = NextTokenTransformer(
            NextTokenConfig(**checkpoint["config"]),
            shapes["obs_dim"],
            shapes["obs_steps"],
            shapes["action_dim"],
            tuple(shapes["scales"]),
            shapes["codebook_size"],
            shapes["num_tasks"],
        )
        transformer.load_state_dict(checkpoint["transformer_state"], strict=True)
        artifact = TokenizerArtifact.from_payload(
            checkpoint["tokenizer"], checkpoint["tokenizer_sha256"], "the policy (the tokenizer it was trained with)"
        )
        normalizers = checkpoint["normalizers"]
        return cls(
            artifact,
            transformer,
            MinMaxNormalizer.from_dict(normalizers["obs"]),
            MinMaxNormalizer.from_dict(normalizers["action"]),
            checkpoint["metadata"],
        )
