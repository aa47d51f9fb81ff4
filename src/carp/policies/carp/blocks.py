"""Transformer pieces: self-attention with a kv-cache, the AdaLN block, and the per-dimension head.

Follows VAR (FoundationVision/VAR, `models/basic_var.py`): pre-norm blocks whose LayerNorms carry no weights of their
own and are modulated by shift/scale/gate vectors computed from the condition. Deviations:

- Modulation vectors are computed by the transformer for all blocks in one projection (see
  :class:`~carp.policies.carp.transformer.CoarseToFineTransformer`) and passed in, instead of one small projection per
  block.
- Attention uses the standard `1/sqrt(head_width)` scale and `F.scaled_dot_product_attention`; a fused qkv projection
  with ordinary biases (VAR: `0.25/sqrt(head_width)`, no key bias).
- The feed-forward activation is exact (erf) GELU; VAR and the official CARP use the tanh approximation, which on
  the CPU is slower than exact GELU both at training size and at inference's batch of one.
- The head scores token `i` against dimension `i % A`'s own vocabulary (weights (A, D, V)); the official CARP shares
  one Linear(D -> V) across dimensions and relies on the position embedding to tell them apart.
"""

import math

import torch
import torch.nn.functional as F
from torch import nn

from carp.policies.carp.attention import BlockCausalPattern, pattern_attention

NORM_EPS = 1e-6
MODULATIONS_PER_BLOCK = 6
"""Shift, scale and gate for the attention branch, then the same for the feed-forward branch."""

AttentionMask = torch.Tensor | BlockCausalPattern | None
"""What a block attends under: a dense (N, N) bool mask, CARP's block-causal pattern, or None (everywhere)."""


class KeyValueCache:
    """Keys and values of the scales already processed, one buffer per block, for K-step inference.

    Each buffer is allocated once per chunk for all L tokens and filled one scale per step, so a step copies only the
    new scale's keys and values. No mask is needed: every cached key belongs to a coarser scale or to the current
    one, all of which the current scale may attend to.

    Args:
        depth: number of blocks.
        capacity: `L`, tokens of a whole chunk.
    """

    def __init__(self, depth: int, capacity: int) -> None:
        self.capacity = capacity
        self.buffers: list[torch.Tensor | None] = [None] * depth
        self.lengths = [0] * depth

    def extend(self, layer_index: int, key_value: torch.Tensor) -> torch.Tensor:
        """Append the current scale's keys and values and return those of all scales so far.

        Args:
            layer_index: block index.
            key_value: (B, s_k * A, 2, Nh, D / Nh), keys then values of the current scale.

        Returns:
            (B, n, 2, Nh, D / Nh), a view of the buffer, with n the number of tokens of scales 1..k.
        """
        buffer = self.buffers[layer_index]
        if buffer is None:
            batch, _, pair, heads, head_width = key_value.shape
            buffer = key_value.new_empty(batch, self.capacity, pair, heads, head_width)
            self.buffers[layer_index] = buffer
        start = self.lengths[layer_index]
        end = start + key_value.shape[1]
        if end > self.capacity:
            raise RuntimeError(f"kv-cache of capacity {self.capacity} cannot hold {end} tokens")
        buffer[:, start:end] = key_value
        self.lengths[layer_index] = end
        return buffer[:, :end]


class SelfAttention(nn.Module):
    """Multi-head self-attention over the token sequence, optionally extending a :class:`KeyValueCache`."""

    def __init__(self, width: int, num_heads: int, dropout: float, layer_index: int) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.head_width = width // num_heads
        self.dropout = dropout
        self.layer_index = layer_index
        self.qkv = nn.Linear(width, 3 * width)
        self.output = nn.Linear(width, width)

    def forward(
        self,
        hidden: torch.Tensor,
        mask: AttentionMask = None,
        cache: KeyValueCache | None = None,
    ) -> torch.Tensor:
        """Attend from every token to the allowed tokens.

        Args:
            hidden: (B, N, D) normalized and modulated tokens.
            mask: the pattern of training over all N = L tokens: an (N, N) bool tensor, True where the query (row)
                may attend the key (column), or CARP's block-causal pattern with its kernel; None attends
                everywhere.
            cache: kv-cache of the coarser scales (inference); its keys precede this call's keys.

        Returns:
            (B, N, D).
        """
        batch, tokens, width = hidden.shape
        # (B, N, 3, Nh, D / Nh) keeps the projection's memory layout: unbinding and transposing are views, and the
        # backward pass stacks the three gradients straight back into this layout without extra copies.
        qkv = self.qkv(hidden).view(batch, tokens, 3, self.num_heads, self.head_width)
        if cache is None:
            query, key, value = qkv.unbind(2)  # (B, N, Nh, D / Nh) each
        else:
            query = qkv[:, :, 0]
            key, value = cache.extend(self.layer_index, qkv[:, :, 1:]).unbind(2)  # (B, n, Nh, D / Nh) each
        attended = _attention(
            query.transpose(1, 2),
            key.transpose(1, 2),
            value.transpose(1, 2),
            mask,
            self.dropout if self.training else 0.0,
        )  # (B, Nh, N, D / Nh)
        attended = attended.transpose(1, 2).reshape(batch, tokens, width)  # (B, N, D)
        return self.output(attended)


def _attention(
    query: torch.Tensor,
    key: torch.Tensor,
    value: torch.Tensor,
    mask: AttentionMask,
    dropout: float,
) -> torch.Tensor:
    """Scaled dot-product attention of (B, Nh, N, d) queries on (B, Nh, n, d) keys and values.

    A block-causal pattern runs its own kernel (`carp.policies.carp.attention`); otherwise one
    `F.scaled_dot_product_attention` call with the (N, N) bool mask (or none), on every device. Under CPU
    autocast (bfloat16 training) attention still runs in float32: PyTorch's CPU flash-attention backward is several
    times slower in bfloat16 than in float32 at this head width (8), more than the casts cost.
    """
    if query.device.type == "cpu" and torch.is_autocast_enabled("cpu"):
        with torch.autocast("cpu", enabled=False):
            return _attention(query.float(), key.float(), value.float(), mask, dropout)
    if isinstance(mask, BlockCausalPattern):
        return pattern_attention(query, key, value, mask, dropout)
    return F.scaled_dot_product_attention(query, key, value, attn_mask=mask, dropout_p=dropout)


class FeedForward(nn.Module):
    """Two-layer MLP with GELU."""

    def __init__(self, width: int, hidden_width: int) -> None:
        super().__init__()
        self.expand = nn.Linear(width, hidden_width)
        self.contract = nn.Linear(hidden_width, width)

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        """Map (B, N, D) to (B, N, D)."""
        return self.contract(F.gelu(self.expand(hidden)))


def modulate(hidden: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Parameter-free LayerNorm followed by the condition's affine map.

    Args:
        hidden: (B, N, D).
        shift: (B, 1, D).
        scale: (B, 1, D), already offset by one so that a zero modulation output means identity scaling.

    Returns:
        (B, N, D).
    """
    return torch.addcmul(shift, F.layer_norm(hidden, hidden.shape[-1:], eps=NORM_EPS), scale)


class AdaptiveBlock(nn.Module):
    """Pre-norm transformer block with adaptive LayerNorm and gated residual branches (VAR's AdaLNSelfAttn)."""

    def __init__(
        self,
        width: int,
        num_heads: int,
        hidden_width: int,
        dropout: float,
        layer_index: int,
    ) -> None:
        super().__init__()
        self.attention = SelfAttention(width, num_heads, dropout, layer_index)
        self.feed_forward = FeedForward(width, hidden_width)
        self.dropout = nn.Dropout(dropout) if dropout > 0 else None

    def forward(
        self,
        hidden: torch.Tensor,
        modulation: tuple[torch.Tensor, ...],
        mask: AttentionMask = None,
        cache: KeyValueCache | None = None,
    ) -> torch.Tensor:
        """Apply attention and feed-forward branches.

        Args:
            hidden: (B, N, D) tokens.
            modulation: `MODULATIONS_PER_BLOCK` tensors (B, 1, D): attention shift, scale, gate, then feed-forward
                shift, scale, gate.
            mask: the training pattern or None, see :class:`SelfAttention`.
            cache: kv-cache for inference, or None.

        Returns:
            (B, N, D).
        """
        attention_shift, attention_scale, attention_gate, mlp_shift, mlp_scale, mlp_gate = modulation
        branch = self.attention(modulate(hidden, attention_shift, attention_scale), mask, cache)
        if self.dropout is not None:
            branch = self.dropout(branch)
        hidden = torch.addcmul(hidden, branch, attention_gate)
        branch = self.feed_forward(modulate(hidden, mlp_shift, mlp_scale))
        if self.dropout is not None:
            branch = self.dropout(branch)
        return torch.addcmul(hidden, branch, mlp_gate)


class PerDimensionHead(nn.Module):
    """Logits of each token over its own dimension's vocabulary: token `i` uses weights of dimension `i % A`.

    Holding one (D, V) matrix per dimension costs the same FLOPs as a shared Linear(D -> V): the sequence is regrouped
    by dimension (every scale's length is a multiple of `A`) and multiplied in one batched matmul, rather than
    computing A*V logits per token and selecting.
    """

    def __init__(self, action_dim: int, width: int, codebook_size: int) -> None:
        super().__init__()
        self.action_dim = action_dim
        self.weight = nn.Parameter(torch.empty(action_dim, width, codebook_size))
        self.bias = nn.Parameter(torch.zeros(action_dim, 1, codebook_size))
        nn.init.trunc_normal_(self.weight, std=1.0 / math.sqrt(width))

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        """Score tokens laid out position-then-dimension.

        Args:
            hidden: (B, N, D) with N a multiple of A and token `i` belonging to dimension `i % A`.

        Returns:
            (B, N, V) logits.
        """
        batch, tokens, _ = hidden.shape
        return self.ungroup(self.grouped_logits(hidden), batch)  # (B, N, V)

    def grouped_logits(self, hidden: torch.Tensor) -> torch.Tensor:
        """Logits in the head's own layout, grouped by dimension: (B, N, D) -> (A, B * N / A, V).

        Row `b * N / A + p` of group `a` is token `p * A + a` of sample `b`; :meth:`group` puts token-aligned tensors
        (such as target ids) in the same order. Training takes the loss in this layout, which saves two copies of the
        largest tensor of a step (forward and backward of the transpose back).
        """
        # Plain views instead of einops ("b (p a) d -> a (b p) d" and back): this runs once per scale at inference,
        # where einops' per-call overhead was measurable.
        grouped = self.group(hidden)  # (A, B * N / A, D)
        return torch.baddbmm(self.bias, grouped, self.weight)  # (A, B * N / A, V)

    def group(self, per_token: torch.Tensor) -> torch.Tensor:
        """(B, N, ...) laid out position-then-dimension -> (A, B * N / A, ...) grouped by dimension."""
        return per_token.reshape(-1, self.action_dim, *per_token.shape[2:]).transpose(0, 1)

    def ungroup(self, grouped: torch.Tensor, batch: int) -> torch.Tensor:
        """Inverse of :meth:`group`: (A, B * N / A, ...) -> (B, N, ...)."""
        return grouped.transpose(0, 1).reshape(batch, -1, *grouped.shape[2:])
