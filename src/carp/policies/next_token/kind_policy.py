"""The next-token policy over the tokens of any tokenizer kind but carp_msvq (`carp.tokenizer.kinds`).

The transformer is the family's (`carp.policies.next_token.transformer`) built with one vocabulary group
(`action_dim` 1) and one level: the kinds other than carp_msvq share one vocabulary among their tokens, so every
position reads the embedding of the previous token from one table and is scored by one head. A fixed-length kind's
sequence is its L tokens over its V ids. A variable-length kind's (FAST) is its tokens followed by an end token (id
V), over V + 1 ids and its maximum + 1 positions (the maximum measured when the kind was fitted); the positions after
the end token are padding, which the loss ignores and the inputs fill with the end token. Generation stops at a
row's end token or after the maximum; a fixed-length kind's after L tokens.

A sequence the kind cannot decode exactly (FAST: a token string that is not H x A coefficients) is repaired by the
kind's `decode` and counted: each prediction reports its repaired chunks (`TimedPrediction.repaired_chunks`), and
the policy keeps running totals. The checkpoint embeds the kind's files and statistics
(`carp.tokenizer.kinds.artifact.KindArtifact.to_payload`) with their sha256, so loading needs no tokenizer folder.
Prediction and serving run in PyTorch: this policy has no ONNX graphs.
"""

import dataclasses
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from carp.config.image_encoder import ImageEncoderConfig
from carp.data.normalizer import MinMaxNormalizer
from carp.policies.base import TimedPrediction
from carp.policies.carp.sampling import check_top_k
from carp.policies.next_token.config import NextTokenConfig
from carp.policies.next_token.generation import generate_sequences
from carp.policies.next_token.transformer import NextTokenTransformer
from carp.policies.observations import checkpoint_image_encoder, restore_observation_encoder
from carp.policies.wrapper import PolicyModule, check_policy_type, check_tokenizer_fit, checkpoint_normalizers
from carp.tokenizer.kinds.artifact import KindArtifact
from carp.tokenizer.kinds.base import ActionTokenizer, TokenBatch, is_variable_length

IGNORED = -100
"""Target of the padding positions, which the cross entropy skips (its `ignore_index`)."""

TOKENIZER_KEY = "tokenizer_kind"
"""Checkpoint entry of the embedded kind; a next-token checkpoint without it holds carp_msvq's artifact."""


@dataclass(frozen=True)
class KindSequence:
    """Where a kind's tokens lie in the transformer's sequence.

    Attributes:
        vocabulary_size: `V`, the kind's token ids [0, V).
        max_tokens: the most tokens of a chunk: `L` for a fixed-length kind, the fitted maximum for a variable one.
        variable_length: whether an end token closes every chunk.
    """

    vocabulary_size: int
    max_tokens: int
    variable_length: bool

    @classmethod
    def of(cls, tokenizer: ActionTokenizer) -> "KindSequence":
        """The sequence of a fitted kind."""
        return cls(tokenizer.vocabulary_size, tokenizer.tokens_per_chunk.maximum, is_variable_length(tokenizer))

    @property
    def end_id(self) -> int | None:
        """Id of the end token (`V`), None for a fixed-length kind."""
        return self.vocabulary_size if self.variable_length else None

    @property
    def output_size(self) -> int:
        """Ids the head scores: `V`, plus the end token for a variable-length kind."""
        return self.vocabulary_size + int(self.variable_length)

    @property
    def positions(self) -> int:
        """Positions of the transformer's sequence: `L`, or the maximum + 1 (room for the end token)."""
        return self.max_tokens + int(self.variable_length)

    def targets(self, tokens: TokenBatch) -> torch.Tensor:
        """(B, P) long target ids: each row's tokens, its end token, then :data:`IGNORED` up to the P positions.

        A row longer than the fitted maximum (a chunk longer than any the kind was fitted on) keeps its first
        `max_tokens` tokens and ends there, as generation does.
        """
        ids = tokens.ids.clone()  # (B, L_max); a copy made outside inference mode, so the loss may keep it
        positions = self.positions
        if ids.shape[1] < positions:
            ids = F.pad(ids, (0, positions - ids.shape[1]), value=IGNORED)
        ids = ids[:, :positions]
        lengths = tokens.lengths.clamp(max=self.max_tokens)  # (B,)
        inside = torch.arange(positions) < lengths[:, None]  # (B, P)
        targets = torch.where(inside, ids, IGNORED)
        if self.variable_length:
            targets[torch.arange(targets.shape[0]), lengths] = self.end_id
        return targets

    def inputs(self, targets: torch.Tensor) -> torch.Tensor:
        """(B, P) ids the transformer reads (shifted by it): the targets with an ignored position's id made valid."""
        return torch.where(targets == IGNORED, self.end_id or 0, targets)


class NextTokenKindPolicy(PolicyModule):
    """Normalizers + a frozen tokenizer of any kind but carp_msvq + the next-token transformer; a `Policy`.

    Args:
        tokenizer_artifact: the registered tokenizer of its kind, with its statistics and sha256; frozen here.
        transformer: the next-token transformer sized for the kind (:meth:`transformer_for`).
        obs_normalizer: min-max statistics of the `Do` low-dim observation features.
        action_normalizer: min-max statistics of the task's `A` action dimensions.
        metadata: plain values stored in the checkpoint.
        image_encoder: the camera encoder's settings for an image policy; None for a state policy.

    Raises:
        ValueError: the transformer was not sized for the kind's sequence.
    """

    policy_type = "next_token"

    def __init__(
        self,
        tokenizer_artifact: KindArtifact,
        transformer: NextTokenTransformer,
        obs_normalizer: MinMaxNormalizer,
        action_normalizer: MinMaxNormalizer,
        metadata: dict[str, Any] | None = None,
        image_encoder: ImageEncoderConfig | None = None,
    ) -> None:
        tokenizer = tokenizer_artifact.tokenizer
        sequence = KindSequence.of(tokenizer)
        pairs = {
            "vocabulary groups": (transformer.action_dim, 1),
            "positions": (transformer.sequence_length, sequence.positions),
            "output ids": (transformer.codebook_size, sequence.output_size),
        }
        check_tokenizer_fit(pairs, "model", f"next-token transformer does not match the {tokenizer.kind} tokenizer")
        super().__init__(
            obs_normalizer, action_normalizer, metadata, transformer.obs_dim, tokenizer.action_dim, image_encoder
        )
        self.tokenizer = tokenizer
        self.tokenizer_artifact = tokenizer_artifact
        self.sequence = sequence
        self.transformer = transformer.eval()
        self.top_k = 1
        self.decoded_chunks = 0
        self.repaired_chunks = 0

    @staticmethod
    def transformer_for(
        config: NextTokenConfig, obs_dim: int, obs_steps: int, tokenizer: ActionTokenizer
    ) -> NextTokenTransformer:
        """The family's transformer sized for a kind: one vocabulary group, its positions and output ids."""
        sequence = KindSequence.of(tokenizer)
        return NextTokenTransformer(config, obs_dim, obs_steps, 1, (sequence.positions,), sequence.output_size)

    @property
    def model_calls_per_chunk(self) -> int:
        """At most `L` (a variable-length kind: its maximum) transformer calls, one per token."""
        return self.sequence.max_tokens

    def configure_inference(self, top_k: int = 1) -> None:
        """Token choice of later predictions: 1 = greedy; k > 1 draws among the k most likely ids (end included)."""
        check_top_k(top_k, self.sequence.output_size)
        self.top_k = top_k

    @property
    def description(self) -> str:
        """`greedy` or `top-<k>`, the token choice of predictions."""
        return "greedy" if self.top_k == 1 else f"top-{self.top_k}"

    @property
    def draws_random(self) -> bool:
        """Top-k choice with k > 1 draws; greedy does not."""
        return self.top_k > 1

    def predict_action_timed(
        self,
        obs: np.ndarray | torch.Tensor,
        task_index: int | np.ndarray | torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        images: np.ndarray | torch.Tensor | None = None,
    ) -> TimedPrediction:
        """Predict each chunk's tokens one at a time, decode them with the kind, and time both parts.

        Args:
            obs: (B, To, Do) raw low-dim observations.
            task_index: see `PolicyModule.task_ids` (None: a multi-task policy's selected task).
            generator: random source of top-k draws, seeded per episode.
            images: (B, To, cameras, 3, h, w) uint8 camera images of an image policy; None for a state policy.

        Returns:
            Actions (B, H, A) raw float32, the two durations in seconds, the calls of the longest row and how many
            of the B chunks the kind had to repair.
        """
        with torch.inference_mode():
            started = time.perf_counter()
            transformer = self.transformer
            features = self.observation_features(obs, transformer.obs_steps, images, task_index)  # (B, To, F)
            encoded = time.perf_counter()
            tokens = generate_sequences(
                transformer, features, self.sequence.max_tokens, self.sequence.end_id, self.top_k, generator
            )
            predicted = time.perf_counter()
            decoded_chunks = self.tokenizer.decode(tokens)
            normalized_actions = decoded_chunks.actions.to(self.device)  # (B, H, A)
            actions = self.action_normalizer.unnormalize(normalized_actions).float().cpu().numpy()
            decoded = time.perf_counter()
        repaired = decoded_chunks.invalid_count
        self.decoded_chunks += len(actions)
        self.repaired_chunks += repaired
        # A row that chose its end token at position p took p + 1 calls; generation stops with the last row.
        calls = min(int(tokens.lengths.max()) + int(self.sequence.variable_length), self.sequence.max_tokens)
        return TimedPrediction(actions, predicted - started, decoded - predicted, calls, encoded - started, repaired)

    def training_loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Mean cross entropy of the teacher-forced logits over every real token and end token (scalar float32).

        Args:
            batch: `obs` (b, To, Do) and `actions` (b, H, A) normalized; `task_ids` (b,) when multi-task; `images`
                (b, To, cameras, 3, h, w) uint8 for an image policy.
        """
        actions = batch["actions"]
        # The kinds encode on the CPU in float32, whatever the loop's device and autocast.
        with torch.no_grad():
            tokens = self.tokenizer.encode(actions.detach().float().cpu())
        targets = self.sequence.targets(tokens).to(actions.device)  # (b, P)
        logits = self.transformer(self.batch_features(batch), self.sequence.inputs(targets))  # (b, P, V')
        return F.cross_entropy(logits.flatten(0, 1).float(), targets.flatten(), ignore_index=IGNORED)

    def family_checkpoint(self) -> dict[str, Any]:
        """The next-token entries: config, shapes, weights, the kind's files and statistics and their sha256."""
        transformer = self.transformer
        return {
            "config": dataclasses.asdict(transformer.config),
            "shapes": {
                "obs_dim": transformer.obs_dim,
                "obs_steps": transformer.obs_steps,
                "action_dim": self.tokenizer.action_dim,
                "positions": transformer.sequence_length,
                "output_ids": transformer.codebook_size,
            },
            "transformer_state": transformer.state_dict(),
            TOKENIZER_KEY: self.tokenizer_artifact.to_payload(),
            "tokenizer_sha256": self.tokenizer_artifact.sha256,
        }

    @classmethod
    def from_checkpoint(cls, checkpoint: dict[str, Any]) -> "NextTokenKindPolicy":
        """Rebuild a policy from :meth:`to_checkpoint` output; the kind's files must hash to the recorded sha256.

        Raises:
            ValueError: another family's checkpoint, or a transformer that does not fit the embedded kind.
            TokenizerMismatchError: the embedded files do not hash to the recorded sha256.
        """
        check_policy_type(checkpoint, cls.policy_type)
        artifact = KindArtifact.from_payload(
            checkpoint[TOKENIZER_KEY], checkpoint["tokenizer_sha256"], "the policy (the tokenizer it was trained with)"
        )
        shapes = checkpoint["shapes"]
        transformer = cls.transformer_for(
            NextTokenConfig(**checkpoint["config"]), shapes["obs_dim"], shapes["obs_steps"], artifact.tokenizer
        )
        transformer.load_state_dict(checkpoint["transformer_state"], strict=True)
        policy = cls(
            artifact,
            transformer,
            *checkpoint_normalizers(checkpoint),
            checkpoint["metadata"],
            checkpoint_image_encoder(checkpoint),
        )
        restore_observation_encoder(policy.observation_encoder, checkpoint)
        return policy
