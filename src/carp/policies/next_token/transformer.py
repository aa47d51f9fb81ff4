"""Next-token autoregressive transformer: CARP's tokens and network, predicted one token at a time.

The conventional next-token baseline of the CARP paper (supplementary, section E): the same registered tokenizer,
the same transformer size and conditioning as CARP (`carp.policies.carp.transformer`), but a causal mask over single
tokens and L sequential steps per chunk instead of K scale steps.

Token order: CARP's own flattened sequence (`carp.policies.carp.layout.TokenLayout`): coarse-to-fine scale by scale,
within a scale position by position, within a position dimension by dimension. Keeping CARP's order and token ids
isolates the one difference the comparison is about, the number of tokens per step: the coarse scales still come
first, so the baseline also keeps CARP's coarse-to-fine prior, and every token id still belongs to dimension
`i % A`'s vocabulary, so CARP's per-dimension head applies unchanged.

Inputs: a GPT-style shifted sequence. Position 0 reads the condition plus a learned start embedding (CARP's first
scale input); position i > 0 reads a learned embedding of token i - 1, one table row per (dimension, id) pair, since
ids of different dimensions index different codebooks. Each position adds CARP's learned position embedding and
the level (scale) embedding of its scale. The condition (flattened `To` observation steps, a multi-task policy's
task embedding included) is projected to `D` and modulates every block through AdaLN, as in CARP. Token embeddings
replace CARP's projected, area-downsampled tokenizer latents because the latent of a partly predicted scale is not
defined one token at a time.

The conditioning, the position and level embeddings, the blocks, the kv-cache and the head are CARP's: the
class extends `carp.policies.carp.transformer.AdaptiveTransformer` and adds only its token inputs and causal mask.
"""

import torch
from torch import nn

from carp.policies.base import check_dimensions
from carp.policies.carp.layout import TokenLayout
from carp.policies.carp.transformer import AdaptiveTransformer, InferenceState
from carp.policies.next_token.config import NextTokenConfig


class NextTokenTransformer(AdaptiveTransformer):
    """Predicts the L token ids of an action chunk one at a time given observation features.

    Args:
        config: the family's config (depth, width, heads, mlp ratio, dropout).
        obs_dim: `Do`, observation features per step.
        obs_steps: `To`, observation steps conditioned on.
        action_dim: `A`, the tokenizer's action dimensions.
        scales: `(s_1, ..., s_K)`, the tokenizer's scales.
        codebook_size: `V`, the tokenizer's vocabulary per dimension.
    """

    def __init__(
        self,
        config: NextTokenConfig,
        obs_dim: int,
        obs_steps: int,
        action_dim: int,
        scales: tuple[int, ...],
        codebook_size: int,
    ) -> None:
        super().__init__()
        check_dimensions(obs_dim=obs_dim, obs_steps=obs_steps, action_dim=action_dim)
        if codebook_size < 2:
            raise ValueError(f"codebook_size must be >= 2, got {codebook_size}")
        self.config = config
        self.action_dim = action_dim
        self.codebook_size = codebook_size
        self.layout = TokenLayout(action_dim, tuple(scales))
        length = self.layout.sequence_length

        self._build_condition(obs_steps, obs_dim, config.width, 1)
        self.token_embedding = nn.Embedding(action_dim * codebook_size, config.width)
        self._build_trunk(self.layout, config, codebook_size)

        dimension_ids = self.layout.dimension_ids()  # (L,)
        self.register_buffer("dimension_ids", dimension_ids, persistent=False)
        # Row of token i's (dimension, id) pair in the embedding table is id + vocabulary_offsets[i].
        self.register_buffer("vocabulary_offsets", dimension_ids * codebook_size, persistent=False)
        causal = torch.ones(length, length, dtype=torch.bool).tril()  # (L, L), True where attending is allowed
        self.register_buffer("causal_mask", causal, persistent=False)
        self._initialize_weights()

    @property
    def sequence_length(self) -> int:
        """`L`, tokens per chunk (and sequential model calls per chunk at inference)."""
        return self.layout.sequence_length

    def forward(self, obs_features: torch.Tensor, token_ids: torch.Tensor) -> torch.Tensor:
        """Teacher-forced logits of all L tokens, each from the condition and the tokens before it.

        Args:
            obs_features: (B, To, F) observation features.
            token_ids: (B, L) long ground-truth ids in sequence order; the last one is never read.

        Returns:
            (B, L, V) logits; row i scores token i against dimension `i % A`'s vocabulary.
        """
        length = self.sequence_length
        if token_ids.dim() != 2 or token_ids.shape[1] != length:
            raise ValueError(f"token_ids must have shape (B, L) = (B, {length}), got {tuple(token_ids.shape)}")
        condition = self.encode_condition(obs_features)  # (B, D)
        modulations = self.modulations(condition)
        previous = self.token_embedding(token_ids[:, :-1] + self.vocabulary_offsets[:-1])  # (B, L - 1, D)
        start = condition.unsqueeze(1) + self.start_embedding  # (B, 1, D)
        hidden = torch.cat((start, previous), dim=1) + self.position_and_level()  # (B, L, D)
        hidden = self.run_blocks(hidden, modulations, self.causal_mask, None)  # (B, L, D)
        return self.head(hidden)  # (B, L, V)

    def next_token_logits(self, state: InferenceState, previous_ids: torch.Tensor | None = None) -> torch.Tensor:
        """Logits of the next token, extending the kv-cache (no mask: every cached key precedes the query).

        Args:
            state: from :meth:`start_inference`, advanced by one token per call.
            previous_ids: None for the first token; afterwards (B,) long, the id chosen at the previous position.

        Returns:
            (B, V) logits of token i = `state.next_step`, over dimension `i % A`'s vocabulary.
        """
        position = state.next_step
        if position >= self.sequence_length:
            raise RuntimeError(f"all {self.sequence_length} tokens were already predicted")
        if position == 0:
            tokens = state.condition.unsqueeze(1) + self.start_embedding  # (B, 1, D)
        else:
            if previous_ids is None:
                raise ValueError(f"token {position} needs the id chosen for token {position - 1}")
            tokens = self.token_embedding(previous_ids + self.vocabulary_offsets[position - 1]).unsqueeze(1)
        hidden = tokens + state.position_and_level[:, position : position + 1]  # (B, 1, D)
        hidden = self.run_blocks(hidden, state.modulations, None, state.cache)  # (B, 1, D)
        state.next_step += 1
        dimension = position % self.action_dim
        return torch.addmm(self.head.bias[dimension, 0], hidden[:, 0], self.head.weight[dimension])  # (B, V)
