"""Token layout of one action chunk and the block-causal attention mask.

docs/architecture.md, "Token layout and attention mask", gives the same rules in prose.

The sequence is scale-major, then position, then dimension: scale k contributes `s_k * A` tokens ordered
`[pos0: d0..d(A-1), pos1: d0..d(A-1), ...]`, so token `i` of any scale belongs to dimension `i % A` (every scale's
length is a multiple of `A`). A token at scale k attends to every token at scales <= k, including the later tokens of
its own scale: all tokens of a scale are predicted in parallel from the coarser scales only.
"""

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class TokenLayout:
    """Index bookkeeping for a chunk of `A` dimensions tokenized at scales `(s_1, ..., s_K)`.

    Attributes:
        action_dim: `A`.
        scales: `(s_1, ..., s_K)`, tokens per dimension at each scale.
    """

    action_dim: int
    scales: tuple[int, ...]

    @property
    def num_scales(self) -> int:
        """`K`."""
        return len(self.scales)

    @property
    def scale_lengths(self) -> tuple[int, ...]:
        """Tokens of each scale in the sequence, `s_k * A`."""
        return tuple(scale * self.action_dim for scale in self.scales)

    @property
    def sequence_length(self) -> int:
        """`L = A * sum(s_k)`."""
        return sum(self.scale_lengths)

    @property
    def scale_bounds(self) -> tuple[tuple[int, int], ...]:
        """`(start, end)` of each scale's tokens in the sequence."""
        bounds = []
        start = 0
        for length in self.scale_lengths:
            bounds.append((start, start + length))
            start += length
        return tuple(bounds)

    def level_ids(self, device: torch.device | str | None = None) -> torch.Tensor:
        """Scale index (0-based) of every token, LongTensor (L,)."""
        lengths = torch.tensor(self.scale_lengths, device=device)
        return torch.repeat_interleave(torch.arange(self.num_scales, device=device), lengths)  # (L,)

    def dimension_ids(self, device: torch.device | str | None = None) -> torch.Tensor:
        """Action dimension whose vocabulary scores each token, LongTensor (L,)."""
        return torch.arange(self.sequence_length, device=device) % self.action_dim  # (L,)

    def attention_mask(self, device: torch.device | str | None = None) -> torch.Tensor:
        """Block-causal mask, BoolTensor (L, L); entry (query, key) is True where the query may attend the key."""
        levels = self.level_ids(device)
        return levels[:, None] >= levels[None, :]  # (L, L)

    # The two reorderings below run once per scale at inference, so they use plain views rather than einops, whose
    # per-call overhead was measurable there; the einops pattern is given in each docstring.

    def scale_tokens_to_ids(self, scale_tokens: torch.Tensor) -> torch.Tensor:
        """Reorder one scale's tokens from sequence order to the tokenizer's per-dimension order.

        Pattern "b (s a) -> b a s".

        Args:
            scale_tokens: (B, s_k * A) token ids in sequence order.

        Returns:
            (B, A, s_k), the tokenizer's layout of the same values.
        """
        return scale_tokens.view(scale_tokens.shape[0], -1, self.action_dim).transpose(1, 2)

    def scale_inputs_to_tokens(self, scale_inputs: torch.Tensor) -> torch.Tensor:
        """Reorder one scale's tokenizer inputs (B, A, C, s_k) to sequence order (B, s_k * A, C).

        Pattern "b a c s -> b (s a) c".
        """
        batch, _, channels, _ = scale_inputs.shape
        return scale_inputs.permute(0, 3, 1, 2).reshape(batch, -1, channels)
