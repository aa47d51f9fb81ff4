"""Smooth synthetic chunks and small tokenizers of every kind (A=3, H=16), fast enough for unit tests."""

import pytest
import torch

from carp.tokenizer.kinds.binning import BinningTokenizer
from carp.tokenizer.kinds.bspline import BSplineTokenizer
from carp.tokenizer.kinds.carp_msvq import CarpMsvqTokenizer
from carp.tokenizer.kinds.fast import FastTokenizer
from carp.tokenizer.kinds.fsq import FsqTokenizer
from carp.tokenizer.kinds.joint_msvq import JointMsvqTokenizer
from carp.tokenizer.kinds.residual_vq import ResidualVqTokenizer
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer

A, H = 3, 16


def smooth_chunks(count: int, seed: int) -> torch.Tensor:
    """(count, H, A) sinusoids of random amplitude, frequency and phase, inside [-1, 1]."""
    generator = torch.Generator().manual_seed(seed)
    time = torch.linspace(0.0, 1.0, H)[None, :, None]
    amplitude = torch.rand(count, 1, A, generator=generator) * 1.6 - 0.8
    frequency = torch.rand(count, 1, A, generator=generator) * 3 + 0.5
    phase = torch.rand(count, 1, A, generator=generator) * 6.0
    return (amplitude * torch.sin(frequency * time + phase) + 0.1 * time).float()


@pytest.fixture(scope="module")
def training_chunks() -> torch.Tensor:
    return smooth_chunks(300, seed=0)


@pytest.fixture(scope="module")
def held_out_chunks() -> torch.Tensor:
    return smooth_chunks(40, seed=1)


def build(kind: str):
    """An unfitted tokenizer of ``kind`` at a small size."""
    if kind == "carp_msvq":
        torch.manual_seed(0)
        spec = TokenizerSpec(action_dim=A, action_horizon=H, scales=(1, 2, 4), codebook_size=16, latent_channels=4)
        return CarpMsvqTokenizer(MultiScaleActionTokenizer(spec))
    return {
        "binning": lambda: BinningTokenizer(A, H, bins=64),
        "fast": lambda: FastTokenizer(A, H, scale=10.0, vocabulary_size=128),
        "bspline": lambda: BSplineTokenizer(A, H, control_points=6, bins=64),
        "fsq": lambda: FsqTokenizer(A, H, levels=(5, 4), downsampling=4, hidden_channels=8, steps=30, batch_size=32),
        "joint_msvq": lambda: JointMsvqTokenizer(
            A, H, scales=(1, 2, 4), codebook_size=16, latent_channels=4, hidden_channels=8, steps=20, batch_size=32
        ),
        "residual_vq": lambda: ResidualVqTokenizer(
            A, H, num_layers=3, num_codes=16, latent_width=16, hidden_width=32, steps=30, batch_size=32
        ),
    }[kind]()


def fitted(kind: str, windows: torch.Tensor):
    """A tokenizer of ``kind`` fitted on ``windows`` (``carp_msvq`` stays untrained: its training is a stage's)."""
    # Module-scoped fixtures call this before the suite's autouse one-thread fixture runs; several threads on a
    # shared machine make these tiny fits many times slower.
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        tokenizer = build(kind)
        if kind != "carp_msvq":
            tokenizer.fit(windows)
    finally:
        torch.set_num_threads(previous)
    return tokenizer
