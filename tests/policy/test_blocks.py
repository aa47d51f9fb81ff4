import pytest
import torch
import torch.nn.functional as F

from carp.policy import blocks
from carp.policy.blocks import (
    BlockCausalMask,
    _attention,
    _blockwise_attention,
    cpu_attention_kernel,
    cpu_prefers_blockwise_attention,
    cpu_vendor,
)
from carp.policy.layout import TokenLayout


def _layout_mask(action_dim: int, scales: tuple[int, ...]) -> BlockCausalMask:
    layout = TokenLayout(action_dim, scales)
    return BlockCausalMask(layout.attention_mask(), tuple(end for _, end in layout.scale_bounds))


def _qkv(batch: int, heads: int, length: int, head_width: int) -> list[torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    # Non-contiguous views, as the transformer passes them: (B, N, Nh, d) transposed to (B, Nh, N, d).
    return [
        torch.randn(batch, length, heads, head_width, generator=generator).transpose(1, 2).requires_grad_()
        for _ in range(3)
    ]


@pytest.mark.parametrize(("action_dim", "scales"), [(10, (1, 2, 3, 4)), (3, (1, 2, 4)), (2, (4,))])
def test_blockwise_attention_equals_dense_masked_attention_and_its_gradients(action_dim, scales):
    mask = _layout_mask(action_dim, scales)
    length = mask.block_ends[-1]
    query, key, value = _qkv(3, 4, length, 8)
    upstream = torch.randn(3, 4, length, 8, generator=torch.Generator().manual_seed(1))

    blockwise = _blockwise_attention(query, key, value, mask.block_ends, 0.0)
    blockwise_grads = torch.autograd.grad(blockwise, (query, key, value), upstream)
    dense = F.scaled_dot_product_attention(query, key, value, attn_mask=mask.dense)
    dense_grads = torch.autograd.grad(dense, (query, key, value), upstream)

    assert blockwise.shape == (3, 4, length, 8)
    torch.testing.assert_close(blockwise, dense, rtol=1e-5, atol=1e-5)
    for mine, reference in zip(blockwise_grads, dense_grads, strict=True):
        torch.testing.assert_close(mine, reference, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("blockwise", [True, False])
def test_cpu_attention_with_a_block_causal_mask_runs_the_kernel_the_cpu_prefers(monkeypatch, blockwise):
    monkeypatch.setattr(blocks._CPU_BLOCKWISE_ATTENTION, "enabled", blockwise)
    mask = _layout_mask(10, (1, 2, 3, 4))
    query, key, value = (tensor.detach() for tensor in _qkv(2, 8, 100, 8))
    attended = _attention(query, key, value, mask, 0.0)
    if blockwise:
        expected = _blockwise_attention(query, key, value, mask.block_ends, 0.0)
    else:
        expected = F.scaled_dot_product_attention(query, key, value, attn_mask=mask.dense)
    torch.testing.assert_close(attended, expected, rtol=0, atol=0)
    # A query of the first scale never sees a later key: changing the last scale's keys leaves it unchanged.
    changed_key = key.clone()
    changed_key[:, :, 60:] += 1.0
    again = _attention(query, changed_key, value, mask, 0.0)
    assert torch.equal(again[:, :, :60], attended[:, :, :60])
    assert not torch.allclose(again[:, :, 60:], attended[:, :, 60:])


def test_blockwise_attention_dropout_drops_weights_only_when_asked():
    mask = _layout_mask(2, (1, 2))
    query, key, value = (tensor.detach() for tensor in _qkv(2, 2, 6, 4))
    plain = _blockwise_attention(query, key, value, mask.block_ends, 0.0)
    torch.manual_seed(0)
    dropped = _blockwise_attention(query, key, value, mask.block_ends, 0.5)
    assert not torch.allclose(plain, dropped)


@pytest.mark.parametrize(
    ("text", "vendor", "blockwise"),
    [
        ("processor\t: 0\nvendor_id\t: GenuineIntel\nflags\t\t: avx2\n", "GenuineIntel", False),
        ("processor\t: 0\nvendor_id\t: AuthenticAMD\n", "AuthenticAMD", True),
        ("processor\t: 0\nCPU implementer\t: 0x41\n", "", True),
    ],
)
def test_cpu_vendor_is_read_from_cpuinfo_and_only_intel_takes_the_masked_kernel(tmp_path, text, vendor, blockwise):
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text(text)
    assert cpu_vendor(cpuinfo) == vendor
    assert cpu_prefers_blockwise_attention(vendor) is blockwise


def test_unreadable_cpuinfo_gives_no_vendor_and_the_blockwise_kernel(tmp_path):
    assert cpu_vendor(tmp_path / "missing") == ""
    assert cpu_prefers_blockwise_attention(cpu_vendor(tmp_path / "missing"))


@pytest.mark.parametrize("blockwise", [True, False])
def test_cpu_attention_kernel_selects_a_kernel_for_its_block_only(blockwise):
    mask = _layout_mask(3, (1, 2, 4))
    query, key, value = (tensor.detach() for tensor in _qkv(2, 4, 21, 8))
    preferred = blocks._CPU_BLOCKWISE_ATTENTION.enabled
    with cpu_attention_kernel(blockwise):
        attended = _attention(query, key, value, mask, 0.0)
        with cpu_attention_kernel(None):
            assert blocks._CPU_BLOCKWISE_ATTENTION.enabled is blockwise
    assert blocks._CPU_BLOCKWISE_ATTENTION.enabled is preferred
    if blockwise:
        expected = _blockwise_attention(query, key, value, mask.block_ends, 0.0)
    else:
        expected = F.scaled_dot_product_attention(query, key, value, attn_mask=mask.dense)
    torch.testing.assert_close(attended, expected, rtol=0, atol=0)
