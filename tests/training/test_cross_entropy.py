import pytest
import torch
import torch.nn.functional as F

from carp.training.cross_entropy import blockwise_cross_entropy


def _logits_and_targets(rows: int, classes: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    logits = (4.0 * torch.randn(rows, classes, generator=generator)).to(dtype)
    return logits, torch.randint(classes, (rows,), generator=generator)


@pytest.mark.parametrize("block_rows", [1, 7, 64, 1000])
def test_float32_loss_and_gradient_equal_torch_cross_entropy(block_rows):
    logits, targets = _logits_and_targets(130, 33, torch.float32)
    ours = logits.clone().requires_grad_()
    reference = logits.clone().requires_grad_()
    loss = blockwise_cross_entropy(ours, targets, block_rows)
    expected = F.cross_entropy(reference, targets)
    (2.5 * loss).backward()
    (2.5 * expected).backward()
    torch.testing.assert_close(loss, expected, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(ours.grad, reference.grad, rtol=1e-5, atol=1e-7)


def test_bfloat16_logits_give_the_float32_loss_and_a_bfloat16_gradient():
    logits, targets = _logits_and_targets(300, 512, torch.bfloat16)
    ours = logits.clone().requires_grad_()
    reference = logits.clone().requires_grad_()
    loss = blockwise_cross_entropy(ours, targets, block_rows=128)
    expected = F.cross_entropy(reference.float(), targets)
    loss.backward()
    expected.backward()
    assert loss.dtype == torch.float32 and ours.grad.dtype == torch.bfloat16
    torch.testing.assert_close(loss, expected, rtol=1e-6, atol=1e-6)
    # Same float32 gradient, rounded once to bfloat16 (8 bits of mantissa) in both.
    torch.testing.assert_close(ours.grad.float(), reference.grad.float(), rtol=2**-7, atol=1e-9)


def test_mismatched_shapes_are_refused():
    logits, targets = _logits_and_targets(10, 5, torch.float32)
    with pytest.raises(ValueError, match=r"logits \(M, V\) and targets \(M,\), got \(10, 5\) and \(9,\)"):
        blockwise_cross_entropy(logits, targets[:9])
