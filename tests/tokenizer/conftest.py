import pytest
import torch

from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer


@pytest.fixture
def tiny_spec() -> TokenizerSpec:
    """A=2, H=8, scales (1, 2), V=8, C=4 (l = 8 / 2**2 = 2)."""
    return TokenizerSpec(action_dim=2, action_horizon=8, scales=(1, 2), codebook_size=8, latent_channels=4)


@pytest.fixture
def tiny_tokenizer(tiny_spec) -> MultiScaleActionTokenizer:
    torch.manual_seed(0)
    return MultiScaleActionTokenizer(tiny_spec).eval()


@pytest.fixture
def tiny_actions(tiny_spec) -> torch.Tensor:
    generator = torch.Generator().manual_seed(1)
    return torch.rand(5, tiny_spec.action_horizon, tiny_spec.action_dim, generator=generator) * 2 - 1
