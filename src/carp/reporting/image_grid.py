"""A grid of sample camera frames per task: one row per camera, one column per sampled step.

Used to check by eye that rendered observations look right (the scene, the objects and the gripper visible, upright,
no missing textures) after the render settings drop shadows, reflections, the skybox and anti-aliasing. Drawn on a
`Figure` with an explicit Agg canvas, so pyplot's global backend is never touched.
"""

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

INCHES_PER_FRAME = 1.6


def sample_steps(length: int, count: int) -> list[int]:
    """``min(count, length)`` evenly spaced step indices from the first to the last step."""
    if length < 1 or count < 1:
        raise ValueError(f"length={length}, count={count}: both must be >= 1")
    return sorted({int(round(step)) for step in np.linspace(0, length - 1, min(count, length))})


def save_frame_grid(
    images: Mapping[str, np.ndarray], path: Path, num_frames: int = 6, title: str | None = None
) -> Path:
    """Save a PNG of evenly spaced frames of every camera.

    Args:
        images: obs key (``<camera>_image``) -> (T, H, W, 3) uint8 upright RGB frames, the same T for every key.
        path: output PNG (parent folders are created).
        num_frames: columns, at most T.
        title: figure title, e.g. the task.

    Returns:
        ``path``.

    Raises:
        ValueError: no cameras, frames that are not (T, H, W, 3) uint8, or cameras of different lengths.
    """
    if not images:
        raise ValueError("no camera images to draw")
    lengths = set()
    for key, frames in images.items():
        if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[-1] != 3:
            raise ValueError(f"images['{key}'] shape={frames.shape}, dtype={frames.dtype}: expected (T, H, W, 3) uint8")
        lengths.add(frames.shape[0])
    if len(lengths) != 1:
        raise ValueError(f"cameras have different numbers of frames: { {k: v.shape[0] for k, v in images.items()} }")
    steps = sample_steps(lengths.pop(), num_frames)
    figure = Figure(figsize=(INCHES_PER_FRAME * len(steps), INCHES_PER_FRAME * len(images) + 0.4))
    FigureCanvasAgg(figure)
    axes = figure.subplots(len(images), len(steps), squeeze=False)
    for row, (key, frames) in enumerate(images.items()):
        for column, step in enumerate(steps):
            axis = axes[row, column]
            axis.imshow(frames[step], interpolation="nearest")
            axis.set_xticks([])
            axis.set_yticks([])
            if row == 0:
                axis.set_title(f"step {step}", fontsize=8)
            if column == 0:
                axis.set_ylabel(key.removesuffix("_image"), fontsize=8)
    if title:
        figure.suptitle(title, fontsize=10)
    figure.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=100)
    return path
