"""Per-feature min-max normalization to [-1, 1] (the convention of Diffusion Policy's low-dim policies).

Constant features (max == min, e.g. an unused gripper joint) map to 0 and back to their constant value instead of
dividing by zero. Statistics are saved as JSON next to the replay buffer and copied into every checkpoint.
"""

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    # Imported where a tensor is normalized, so that the data stages (collect, ingest) start without loading torch.
    import torch

# Below this range a feature counts as constant: float32 noise in a recorded constant would otherwise be blown up.
CONSTANT_RANGE = 1e-6


@dataclass(frozen=True)
class MinMaxNormalizer:
    """Maps each feature's [min, max] to [-1, 1].

    Attributes:
        minimum: (F,) per-feature minimum.
        maximum: (F,) per-feature maximum.
    """

    minimum: np.ndarray
    maximum: np.ndarray

    @classmethod
    def fit(cls, values: np.ndarray) -> "MinMaxNormalizer":
        """Fit on (N, F) values (features along the last axis).

        Raises:
            ValueError: a feature's minimum, maximum or range is not finite in float32, the dtype of the data it
                normalizes (the replay buffer's); the message names the feature.
        """
        flat = np.asarray(values, dtype=np.float64).reshape(-1, values.shape[-1])
        minimum, maximum = flat.min(axis=0), flat.max(axis=0)
        with np.errstate(over="ignore", invalid="ignore"):
            low, high = minimum.astype(np.float32), maximum.astype(np.float32)
            finite = np.isfinite(low) & np.isfinite(high) & np.isfinite(high - low)
        if not finite.all():
            feature = int(np.flatnonzero(~finite)[0])
            raise ValueError(
                f"feature {feature}: minimum={minimum[feature]!r}, maximum={maximum[feature]!r}: the statistics or "
                "their range are not finite in float32"
            )
        return cls(minimum=minimum, maximum=maximum)

    @property
    def num_features(self) -> int:
        """F."""
        return int(self.minimum.shape[0])

    def half_range(self) -> np.ndarray:
        """(F,) original units per normalized unit: (max - min) / 2, or 0 for a constant feature."""
        span = self.maximum - self.minimum
        return np.where(span < CONSTANT_RANGE, 0.0, span / 2.0)

    def _scale_offset(self) -> tuple[np.ndarray, np.ndarray]:
        span = self.maximum - self.minimum
        constant = span < CONSTANT_RANGE
        scale = np.where(constant, 1.0, 2.0 / np.where(constant, 1.0, span))
        # Constant features: normalized = 0 exactly, un-normalized = their value.
        offset = np.where(constant, -self.minimum, -1.0 - self.minimum * scale)
        return scale, offset

    def normalize(self, values: "np.ndarray | torch.Tensor") -> "np.ndarray | torch.Tensor":
        """(..., F) raw -> (..., F) in [-1, 1]; keeps the input's array type, dtype and device."""
        scale, offset = self._scale_offset()
        return values * self._like(scale, values) + self._like(offset, values)

    def unnormalize(self, values: "np.ndarray | torch.Tensor") -> "np.ndarray | torch.Tensor":
        """(..., F) in [-1, 1] -> (..., F) raw; inverse of :meth:`normalize`.

        Constant features come back as their constant whatever the input, so a model's stray output on a dimension
        the data never moved cannot drift it.
        """
        scale, offset = self._scale_offset()
        constant = self.maximum - self.minimum < CONSTANT_RANGE
        # For constant features: scale 0 and offset = min, so the result is exactly min.
        scale_back = np.where(constant, 0.0, 1.0 / scale)
        offset_back = np.where(constant, self.minimum, -offset / scale)
        return values * self._like(scale_back, values) + self._like(offset_back, values)

    @staticmethod
    def _like(array: np.ndarray, reference: "np.ndarray | torch.Tensor") -> "np.ndarray | torch.Tensor":
        if isinstance(reference, np.ndarray | np.generic):
            return array.astype(reference.dtype if np.issubdtype(reference.dtype, np.floating) else np.float64)
        import torch

        return torch.as_tensor(array, dtype=reference.dtype, device=reference.device)

    def to_dict(self) -> dict[str, list[float]]:
        """JSON-ready form."""
        return {"minimum": self.minimum.tolist(), "maximum": self.maximum.tolist()}

    @classmethod
    def from_dict(cls, state: dict[str, list[float]]) -> "MinMaxNormalizer":
        """Inverse of :meth:`to_dict`."""
        return cls(minimum=np.asarray(state["minimum"], dtype=np.float64), maximum=np.asarray(state["maximum"]))


def save_normalizers(path: Path, normalizers: dict[str, MinMaxNormalizer]) -> None:
    """Write named normalizers (e.g. ``obs``, ``action``) as one JSON file."""
    Path(path).write_text(json.dumps({name: n.to_dict() for name, n in normalizers.items()}, indent=2))


def load_normalizers(path: Path) -> dict[str, MinMaxNormalizer]:
    """Read a file written by :func:`save_normalizers`."""
    raw = json.loads(Path(path).read_text())
    return {name: MinMaxNormalizer.from_dict(state) for name, state in raw.items()}
