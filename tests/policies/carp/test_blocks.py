import pytest
import torch
import torch.nn.functional as F

from carp.policies.carp.blocks import _attention
from carp.policies.carp.layout import TokenLayout


def _qkv(batch: int, heads: int, length: int, head_width: int) -> list[torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    # Non-contiguous views, as the transformer passes them: (B, N, Nh, d) transposed to (B, Nh, N, d).
    return [torch.randn(batch, length, heads, head_width, generator=generator).transpose(1, 2) for _ in range(3)]


@pytest.mark.parametrize(("action_dim", "scales"), [(10, (1, 2, 3, 4)), (3, (1, 2, 4))])
def test_training_attention_is_block_causal(action_dim, scales):
    layout = TokenLayout(action_dim, scales)
    mask = layout.attention_mask()
    length = layout.scale_bounds[-1][1]
    first_scale_end = layout.scale_bounds[0][1]
    last_scale_start = layout.scale_bounds[-1][0]
    query, key, value = _qkv(2, 4, length, 8)

    attended = _attention(query, key, value, mask, 0.0)
    expected = F.scaled_dot_product_attention(query, key, value, attn_mask=mask)
    torch.testing.assert_close(attended, expected, rtol=0, atol=0)
    # Changing the last scale's keys and values leaves every coarser scale's output unchanged, and changes the last.
    changed_key, changed_value = key.clone(), value.clone()
    changed_key[:, :, last_scale_start:] += 1.0
    changed_value[:, :, last_scale_start:] -= 1.0
    again = _attention(query, changed_key, changed_value, mask, 0.0)
    assert torch.equal(again[:, :, :last_scale_start], attended[:, :, :last_scale_start])
    assert not torch.allclose(again[:, :, last_scale_start:], attended[:, :, last_scale_start:])
    # The first scale sees only itself: its output is the same as attention over the first scale alone.
    alone = F.scaled_dot_product_attention(
        query[:, :, :first_scale_end], key[:, :, :first_scale_end], value[:, :, :first_scale_end]
    )
    torch.testing.assert_close(attended[:, :, :first_scale_end], alone, rtol=1e-6, atol=1e-6)


def test_training_attention_dropout_drops_weights_only_when_asked():
    layout = TokenLayout(2, (1, 2))
    query, key, value = _qkv(2, 2, 6, 4)
    mask = layout.attention_mask()
    plain = _attention(query, key, value, mask, 0.0)
    torch.manual_seed(0)
    dropped = _attention(query, key, value, mask, 0.5)
    assert not torch.allclose(plain, dropped)
