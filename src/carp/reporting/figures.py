"""What every report figure does last: legend, grid, layout, a PNG on disk, the figure released."""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def finish_figure(figure, axis, path: Path) -> Path:
    """Legend, grid, tight layout; save as PNG at `path` (its folder created) and release the figure."""
    axis.legend(fontsize=7)
    axis.grid(alpha=0.3)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path
