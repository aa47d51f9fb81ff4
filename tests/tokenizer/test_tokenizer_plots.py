import numpy as np
import pytest
import torch

from carp.tokenizer.plots import plot_reconstruction


def test_plot_writes_a_png(tmp_path):
    steps = np.linspace(0, 1, 40)
    raw = np.stack([np.sin(steps * 6), np.cos(steps * 3), np.sign(steps - 0.5)], axis=1)
    path = plot_reconstruction(
        raw,
        torch.as_tensor(raw * 0.95),
        tmp_path / "figures" / "reconstruction.png",
        ["x", "y", "gripper"],
        title="Lift",
    )
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(data) > 10_000


def test_plot_checks_shapes_and_names(tmp_path):
    raw = np.zeros((10, 2))
    with pytest.raises(ValueError, match="must both be"):
        plot_reconstruction(raw, np.zeros((10, 3)), tmp_path / "bad.png", ["a", "b"])
    with pytest.raises(ValueError, match="expected 2 dimension names, got 1"):
        plot_reconstruction(raw, raw, tmp_path / "bad.png", ["a"])
