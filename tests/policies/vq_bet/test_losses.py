"""Focal loss against cross entropy and a value computed by hand."""

import math

import pytest
import torch
import torch.nn.functional as F

from carp.policies.vq_bet.losses import focal_loss


def test_gamma_zero_is_cross_entropy():
    logits = torch.randn(10, 5, generator=torch.Generator().manual_seed(0))
    targets = torch.arange(10) % 5
    assert torch.allclose(focal_loss(logits, targets, 0.0), F.cross_entropy(logits, targets))


def test_known_value_and_down_weighting_of_easy_samples():
    logits = torch.log(torch.tensor([[0.9, 0.1], [0.2, 0.8]]))
    targets = torch.tensor([0, 0])
    expected = -((0.1**2) * math.log(0.9) + (0.8**2) * math.log(0.2)) / 2
    assert focal_loss(logits, targets, 2.0).item() == pytest.approx(expected, rel=1e-5)
    assert focal_loss(logits, targets, 2.0) < F.cross_entropy(logits, targets)


def test_negative_gamma_is_refused():
    with pytest.raises(ValueError, match="gamma"):
        focal_loss(torch.zeros(1, 2), torch.zeros(1, dtype=torch.long), -1.0)
