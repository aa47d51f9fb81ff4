"""Transformer pieces: self-attention with a kv-cache, the AdaLN block, and the per-dimension head.

Follows VAR (FoundationVision/VAR, `models/basic_var.py`): pre-norm blocks whose LayerNorms carry no weights of their
own and are modulated by shift/scale/gate vectors computed from the condition. Deviations:

- Modulation vectors are computed by the transformer for all blocks in one projection (see
  :class:`~carp.policy.transformer.CoarseToFineTransformer`) and passed in, instead of one small projection per block.
- Attention uses the standard `1/sqrt(head_width)` scale and `F.scaled_dot_product_attention`; a fused qkv projection
  with ordinary biases (VAR: `0.25/sqrt(head_width)`, no key bias).
- The feed-forward activation is exact (erf) GELU; VAR and the official CARP use the tanh approximation, which on
  CPU measured ~4x slower than exact GELU at training size (25,600 x 256 elements) and no faster at inference size.
- The head scores token `i` against dimension `i % A`'s own vocabulary (weights (A, D, V)); the official CARP shares
  one Linear(D -> V) across dimensions and relies on the position embedding to tell them apart.
"""

import math

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

NORM_EPS = 1e-6
MODULATIONS_PER_BLOCK = 6
"""Shift, scale and gate for the attention branch, then the same for the feed-forward branch."""


class KeyValueCache:
    """Keys and values of the scales already processed, one entry per block, for K-step inference.

    The entries grow by one scale per step; no mask is needed because every cached key belongs to a coarser scale
    (or to the current one), all of which the current scale may attend to.
    """

    def __init__(self, depth: int) -> None:
        self.entries: list[torch.Tensor | None] = [None] * depth

    def extend(self, layer_index: int, key_value: torch.Tensor) -> torch.Tensor:
        """Append the current scale's keys and values and return those of all scales so far.

        Args:
            layer_index: block index.
            key_value: (2, B, Nh, s_k * A, D / Nh), keys then values of the current scale.

        Returns:
            (2, B, Nh, n, D / Nh) with n the number of tokens of scales 1..k.
        """
        past = self.entries[layer_index]
        if past is not None:
            key_value = torch.cat((past, key_value), dim=3)  # (2, B, Nh, n, D / Nh)
        self.entries[layer_index] = key_value
        return key_value


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
        attention_mask: torch.Tensor | None = None,
        cache: KeyValueCache | None = None,
    ) -> torch.Tensor:
        """Attend from every token to the allowed tokens.

        Args:
            hidden: (B, N, D) normalized and modulated tokens.
            attention_mask: (N, N) bool, True where a query may attend a key; None attends everywhere.
            cache: kv-cache of the coarser scales (inference); its keys precede this call's keys.

        Returns:
            (B, N, D).
        """
        batch, tokens, width = hidden.shape
        qkv = self.qkv(hidden).view(batch, tokens, 3, self.num_heads, self.head_width)
        qkv = qkv.permute(2, 0, 3, 1, 4)  # (3, B, Nh, N, D / Nh)
        query, key_value = qkv[0], qkv[1:]
        if cache is not None:
            key_value = cache.extend(self.layer_index, key_value)  # (2, B, Nh, n, D / Nh)
        attended = F.scaled_dot_product_attention(
            query,
            key_value[0],
            key_value[1],
            attn_mask=attention_mask,
            dropout_p=self.dropout if self.training else 0.0,
        )  # (B, Nh, N, D / Nh)
        attended = attended.transpose(1, 2).reshape(batch, tokens, width)  # (B, N, D)
        return self.output(attended)


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
        attention_mask: torch.Tensor | None = None,
        cache: KeyValueCache | None = None,
    ) -> torch.Tensor:
        """Apply attention and feed-forward branches.

        Args:
            hidden: (B, N, D) tokens.
            modulation: `MODULATIONS_PER_BLOCK` tensors (B, 1, D): attention shift, scale, gate, then feed-forward
                shift, scale, gate.
            attention_mask: (N, N) bool or None, see :class:`SelfAttention`.
            cache: kv-cache for inference, or None.

        Returns:
            (B, N, D).
        """
        attention_shift, attention_scale, attention_gate, mlp_shift, mlp_scale, mlp_gate = modulation
        branch = self.attention(modulate(hidden, attention_shift, attention_scale), attention_mask, cache)
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
        batch = hidden.shape[0]
        grouped = rearrange(hidden, "b (p a) d -> a (b p) d", a=self.action_dim)  # (A, B * N / A, D)
        logits = torch.baddbmm(self.bias, grouped, self.weight)  # (A, B * N / A, V)
        return rearrange(logits, "a (b p) v -> b (p a) v", b=batch)  # (B, N, V)
