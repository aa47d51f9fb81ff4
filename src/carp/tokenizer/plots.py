"""Raw vs reconstructed action figure in the style of the CARP paper's Fig. 7 (blue raw, red reconstruction).

Figures are drawn on a `Figure` with an explicit Agg canvas, so the module never touches pyplot's global backend
state and works headless.
"""

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

RAW_COLOR = "tab:blue"
RECONSTRUCTED_COLOR = "tab:red"
MAX_COLUMNS = 5


def _as_array(values: np.ndarray | torch.Tensor) -> np.ndarray:
    if isinstance(values, torch.Tensor):
        values = values.detach().cpu().numpy()
    return np.asarray(values, dtype=np.float64)


def plot_reconstruction(
    raw: np.ndarray | torch.Tensor,
    reconstructed: np.ndarray | torch.Tensor,
    path: Path,
    dimension_names: Sequence[str],
    title: str | None = None,
) -> Path:
    """Save a PNG with one subplot per action dimension: raw (blue) and reconstructed (red) over time.

    Args:
        raw: (T, A) actions in original units.
        reconstructed: (T, A) tokenizer reconstruction in the same units.
        path: output PNG path (parent directories are created).
        dimension_names: A subplot titles.
        title: optional figure title.

    Returns:
        The written path.
    """
    raw, reconstructed = _as_array(raw), _as_array(reconstructed)
    if raw.ndim != 2 or raw.shape != reconstructed.shape:
        raise ValueError(f"raw and reconstructed must both be (T, A), got {raw.shape} and {reconstructed.shape}")
    num_dimensions = raw.shape[1]
    if len(dimension_names) != num_dimensions:
        raise ValueError(f"expected {num_dimensions} dimension names, got {len(dimension_names)}")

    columns = min(MAX_COLUMNS, num_dimensions)
    rows = math.ceil(num_dimensions / columns)
    figure = Figure(figsize=(3.2 * columns, 2.4 * rows), layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.subplots(rows, columns, squeeze=False)
    steps = np.arange(raw.shape[0])
    for dimension, axis in enumerate(axes.flat):
        if dimension >= num_dimensions:
            axis.set_visible(False)
            continue
        axis.plot(steps, raw[:, dimension], color=RAW_COLOR, linewidth=1.4, label="raw")
        axis.plot(steps, reconstructed[:, dimension], color=RECONSTRUCTED_COLOR, linewidth=1.0, label="reconstructed")
        axis.set_title(dimension_names[dimension], fontsize=10)
        axis.tick_params(labelsize=8)
        axis.grid(alpha=0.3)
    axes.flat[0].legend(fontsize=8, loc="best")
    for axis in axes[-1]:
        axis.set_xlabel("step", fontsize=9)
    if title:
        figure.suptitle(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    return path
