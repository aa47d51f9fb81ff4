"""Coarse-to-fine autoregressive transformer: next-scale prediction of action tokens.

Overview in docs/architecture.md, "Coarse-to-fine transformer".

Follows VAR (FoundationVision/VAR, `models/var.py`) and the official CARP (`singletask/CFAP/autoreg.py`): a
decoder-only GPT-2-style stack with AdaLN conditioning. The first scale's tokens are the condition plus a learned
start embedding; scale k > 1 reads a linear projection of the tokenizer latent accumulated from scales < k,
area-downsampled to `s_k`. A learned per-token position embedding and a per-scale level embedding are added.
Training is teacher-forced under a block-causal mask; inference runs K steps with a kv-cache.

Deviations from those sources: the condition comes from the flattened observation features (a multi-task policy's
task embedding included) rather than a class label, so there is no classifier-free guidance; all AdaLN modulations
(every block's and the head's) come from one projection of SiLU(cond) that inference computes once per chunk instead
of once per block and scale; the head has one vocabulary per action dimension (see
:class:`~carp.policies.carp.blocks.PerDimensionHead`).
"""

import math
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from carp.policies.carp.attention import BlockCausalPattern
from carp.policies.carp.blocks import (
    MODULATIONS_PER_BLOCK,
    AdaptiveBlock,
    AttentionMask,
    KeyValueCache,
    PerDimensionHead,
    modulate,
)
from carp.policies.carp.layout import TokenLayout
from carp.policies.carp.spec import PolicySpec

EMBEDDING_INIT_STD = 0.02
GATE_INIT_GAIN = 1e-5
"""Gates start near zero so every block starts close to the identity (VAR's `init_adaln_gamma`)."""
HEAD_INIT_GAIN = 0.02
"""Near-uniform initial logits (VAR's `init_head`)."""


@dataclass
class InferenceState:
    """What cached inference carries from one sequential call to the next (K scale steps or L token steps).

    Attributes:
        condition: (B, D) condition vector.
        modulations: tensors (B, 1, D): `MODULATIONS_PER_BLOCK` per block, then the head's shift and scale.
        position_and_level: (1, L, D) position plus level embedding of every token.
        cache: keys and values of the tokens processed so far.
        next_step: index (0-based) of the step the next call predicts: a scale for CARP, a token for next-token.
    """

    condition: torch.Tensor
    modulations: tuple[torch.Tensor, ...]
    position_and_level: torch.Tensor
    cache: KeyValueCache
    next_step: int = 0


class AdaptiveTransformer(nn.Module):
    """The parts CARP's transformer and the next-token transformer share.

    Those are the AdaLN conditioning on the observation features, the learned position and level embeddings, the
    block stack and the modulated input of the head. A subclass builds itself in this order:
    :meth:`_build_condition`, its own token inputs, :meth:`_build_trunk`, then :meth:`_initialize_weights`. The
    order fixes the registration order of the parameters, hence the seeded initial weights and the names of the
    checkpoint's entries.
    """

    def _build_condition(self, obs_steps: int, obs_dim: int, width: int, start_length: int) -> None:
        """The condition: the projection of the observation features to `D` and the first tokens' start embedding.

        Args:
            obs_steps: `To`.
            obs_dim: `F`, features per step (a multi-task policy's task embedding included).
            width: `D`.
            start_length: tokens of the first step (CARP: `s_1 * A`; next-token: 1).
        """
        self.obs_steps, self.obs_dim = obs_steps, obs_dim
        self.condition_projection = nn.Linear(obs_steps * obs_dim, width)
        self.start_embedding = nn.Parameter(torch.empty(1, start_length, width))

    def _build_trunk(self, layout: TokenLayout, architecture: Any, codebook_size: int) -> None:
        """Position and level embeddings, the AdaLN modulation projection, the blocks and the per-dimension head.

        Args:
            layout: the chunk's token layout (`L`, the scales, `A`).
            architecture: `depth`, `width`, `num_heads`, `hidden_width` and `dropout` (the family's config).
            codebook_size: `V`.
        """
        depth, width = architecture.depth, architecture.width
        self.depth, self.width = depth, width
        self.position_embedding = nn.Parameter(torch.empty(1, layout.sequence_length, width))
        self.level_embedding = nn.Parameter(torch.empty(layout.num_scales, width))

        self.num_modulations = MODULATIONS_PER_BLOCK * depth + 2
        self.modulation = nn.Linear(width, self.num_modulations * width)
        # Scale modulations are applied as (1 + scale); adding the one here once saves an op per use.
        scale_rows = torch.zeros(self.num_modulations, 1)
        scale_rows[1 : MODULATIONS_PER_BLOCK * depth : 3] = 1.0
        scale_rows[-1] = 1.0
        self.register_buffer("modulation_offset", scale_rows.expand(-1, width).reshape(-1), persistent=False)

        self.blocks = nn.ModuleList(
            AdaptiveBlock(width, architecture.num_heads, architecture.hidden_width, architecture.dropout, index)
            for index in range(depth)
        )
        self.head = PerDimensionHead(layout.action_dim, width, codebook_size)
        self.register_buffer("level_ids", layout.level_ids(), persistent=False)

    def _initialize_weights(self) -> None:
        initialize_adaptive_transformer(self, self.depth, self.width)

    def encode_condition(self, obs_features: torch.Tensor) -> torch.Tensor:
        """Project the observation features to the condition vector.

        Args:
            obs_features: (B, To, F) observation features (or already flattened (B, To * F)).

        Returns:
            (B, D) condition.
        """
        features = obs_features.reshape(obs_features.shape[0], -1)  # (B, To * F)
        expected = self.obs_steps * self.obs_dim
        if features.shape[1] != expected:
            raise ValueError(
                f"observations have {features.shape[1]} features per sample ({tuple(obs_features.shape)}), "
                f"expected To * Do = {self.obs_steps} * {self.obs_dim} = {expected}"
            )
        return self.condition_projection(features)  # (B, D)

    def modulation_vector(self, condition: torch.Tensor) -> torch.Tensor:
        """The M AdaLN vectors of a condition (B, D) side by side, (B, M * D), in the order of `modulations`."""
        return self.modulation(F.silu(condition)) + self.modulation_offset  # (B, M * D)

    def modulations(self, condition: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """AdaLN vectors (B, 1, D) of a condition (B, D): shift, 1 + scale, gate per block branch, then the head's."""
        modulation = self.modulation_vector(condition)  # (B, M * D)
        return modulation.view(condition.shape[0], self.num_modulations, 1, self.width).unbind(1)

    def position_and_level(self) -> torch.Tensor:
        """Position plus level embedding of every token, (1, L, D)."""
        return self.position_embedding + self.level_embedding[self.level_ids]  # (1, L, D)

    def empty_cache(self) -> KeyValueCache:
        """A kv-cache for one chunk: every block's keys and values of up to L tokens."""
        return KeyValueCache(self.depth, self.position_embedding.shape[1])

    def start_inference(self, obs_features: torch.Tensor) -> InferenceState:
        """Encode the condition, its modulations and the position embeddings once, and open an empty kv-cache.

        Args:
            obs_features: (B, To, F) observation features.

        Returns:
            State to pass to the subclass's step method once per sequential call.
        """
        condition = self.encode_condition(obs_features)  # (B, D)
        return InferenceState(condition, self.modulations(condition), self.position_and_level(), self.empty_cache())

    def run_blocks(
        self,
        hidden: torch.Tensor,
        modulations: tuple[torch.Tensor, ...],
        mask: AttentionMask,
        cache: KeyValueCache | None = None,
    ) -> torch.Tensor:
        """The blocks, then the head's modulated LayerNorm: the head's input.

        Args:
            hidden: (B, N, D) token inputs plus their position and level embeddings.
            modulations: from :meth:`modulations`.
            mask: (N, N) bool, True where attending is allowed, or CARP's block-causal pattern; None when every key
                may be attended.
            cache: keys and values of earlier tokens, extended by this call; None for a full forward pass.

        Returns:
            (B, N, D).
        """
        for index, block in enumerate(self.blocks):
            start = index * MODULATIONS_PER_BLOCK
            hidden = block(hidden, modulations[start : start + MODULATIONS_PER_BLOCK], mask, cache)
        shift, scale = modulations[-2:]
        return modulate(hidden, shift, scale)  # (B, N, D)


class CoarseToFineTransformer(AdaptiveTransformer):
    """Predicts the token ids of every scale of an action chunk given observation features.

    Args:
        spec: the shapes of data and tokenizer, and CARP's params section (the architecture).
    """

    def __init__(self, spec: PolicySpec) -> None:
        super().__init__()
        self.spec = spec
        self.layout = TokenLayout(spec.action_dim, spec.scales)
        width = spec.config.width
        self._build_condition(spec.obs_steps, spec.obs_dim, width, self.layout.scale_lengths[0])
        self.token_projection = nn.Linear(spec.latent_channels, width)
        self._build_trunk(self.layout, spec.config, spec.codebook_size)
        self.register_buffer("attention_mask", self.layout.attention_mask(), persistent=False)
        self.attention_kernel = "masked"
        """Kernel of the block-causal training attention, "masked" or "blockwise" (`carp.policies.carp.attention`)."""
        self._initialize_weights()

    def training_pattern(self) -> BlockCausalPattern:
        """The block-causal pattern of teacher-forced training, computed by `attention_kernel`."""
        block_ends = tuple(end for _, end in self.layout.scale_bounds)
        return BlockCausalPattern(self.attention_mask, block_ends, self.attention_kernel)

    def _first_scale_tokens(self, condition: torch.Tensor) -> torch.Tensor:
        return condition.unsqueeze(1) + self.start_embedding  # (B, s_1 * A, D)

    def forward(
        self,
        obs_features: torch.Tensor,
        teacher_inputs: torch.Tensor,
        grouped_by_dimension: bool = False,
    ) -> torch.Tensor:
        """Teacher-forced logits of all L tokens.

        Args:
            obs_features: (B, To, F) observation features.
            teacher_inputs: (B, L - s_1 * A, C) float, the tokenizer's teacher-forcing inputs of scales 2..K in
                sequence order (area-downsampled accumulated latent of the ground-truth tokens of coarser scales).
            grouped_by_dimension: return the logits in the head's layout (see
                :meth:`~carp.policies.carp.blocks.PerDimensionHead.grouped_logits`), as training uses them.

        Returns:
            (B, L, V) logits; token `i` is scored against dimension `i % A`'s vocabulary. With
            `grouped_by_dimension`: (A, B * L / A, V).
        """
        condition = self.encode_condition(obs_features)  # (B, D)
        modulations = self.modulations(condition)
        tokens = torch.cat(
            (self._first_scale_tokens(condition), self.token_projection(teacher_inputs)), dim=1
        )  # (B, L, D)
        hidden = self.run_blocks(tokens + self.position_and_level(), modulations, self.training_pattern())  # (B, L, D)
        if grouped_by_dimension:
            return self.head.grouped_logits(hidden)  # (A, B * L / A, V)
        return self.head(hidden)  # (B, L, V)

    def next_scale_logits(self, state: InferenceState, scale_inputs: torch.Tensor | None = None) -> torch.Tensor:
        """Logits of the next scale's tokens, extending the kv-cache (no mask: cached keys are all coarser scales).

        Args:
            state: from :meth:`start_inference`, advanced by one scale per call.
            scale_inputs: None for the first scale; afterwards (B, s_k * A, C) float, the area-downsampled latent
                accumulated from the predicted scales, in sequence order.

        Returns:
            (B, s_k * A, V) logits of scale k = `state.next_step`.
        """
        scale_index = state.next_step
        if scale_index >= self.layout.num_scales:
            raise RuntimeError(f"all {self.layout.num_scales} scales were already predicted")
        start, end = self.layout.scale_bounds[scale_index]
        if scale_index == 0:
            tokens = self._first_scale_tokens(state.condition)  # (B, s_1 * A, D)
        else:
            if scale_inputs is None:
                raise ValueError(f"scale {scale_index + 1} needs the accumulated latent of the coarser scales")
            tokens = self.token_projection(scale_inputs)  # (B, s_k * A, D)
        hidden = self.run_blocks(tokens + state.position_and_level[:, start:end], state.modulations, None, state.cache)
        state.next_step += 1
        return self.head(hidden)  # (B, s_k * A, V)


def initialize_adaptive_transformer(model: nn.Module, depth: int, width: int) -> None:
    """Initialize a transformer of AdaLN blocks in place, as CARP does (VAR's scheme).

    Shared by every family built on these blocks (CARP, next-token). ``model`` holds ``blocks``, ``modulation`` (its
    ``num_modulations`` (D, D) matrices stacked), ``head``, ``start_embedding``, ``position_embedding`` and
    ``level_embedding``. The order of the draws is fixed, so a seeded model is the same whichever family builds it.
    """
    for module in model.modules():
        if isinstance(module, nn.Linear):
            nn.init.trunc_normal_(module.weight, std=EMBEDDING_INIT_STD)
            nn.init.zeros_(module.bias)
        elif isinstance(module, nn.Embedding):
            nn.init.trunc_normal_(module.weight, std=EMBEDDING_INIT_STD)
    for parameter in (model.start_embedding, model.position_embedding, model.level_embedding):
        nn.init.trunc_normal_(parameter, std=EMBEDDING_INIT_STD)
    # GPT-2: residual branch outputs shrink with depth so the residual stream's variance stays bounded.
    residual_gain = 1.0 / math.sqrt(2 * depth)
    for block in model.blocks:
        block.attention.output.weight.data.mul_(residual_gain)
        block.feed_forward.contract.weight.data.mul_(residual_gain)
    weight = model.modulation.weight.data.view(model.num_modulations, width, width)
    weight[2 : MODULATIONS_PER_BLOCK * depth : 3].mul_(GATE_INIT_GAIN)
    model.head.weight.data.mul_(HEAD_INIT_GAIN)
