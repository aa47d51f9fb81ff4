"""Zero padding of one task's low-dim observations to the wider layout a multi-task policy shares with other tasks.

Tasks of one multi-task policy observe the same keys in the same order, but a key may be wider in one task than in
another (the `object` state: 10 features in Lift, 14 in Can, 23 in Stack, 28 in NutAssembly). The policy takes the
widest layout: each key gets the largest width any of its tasks has, and a task's features of that key fill the
key's first columns, the rest being zero. A padded column is therefore a constant of its task's data, which the
task's min-max statistics map to 0 (`carp.data.normalizer`), so it carries nothing but the absence of a feature;
the task embedding tells the policy which task's meaning the shared columns have.

Padding happens inside the policy (`carp.policies.wrapper.PolicyModule.observation_features` and CARP's exported
graphs), so the simulator, the evaluation rollout and a served robot keep sending each task's own observations.
"""

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from carp.data.normalizer import MinMaxNormalizer


@dataclass(frozen=True)
class ObservationPadding:
    """How one task's observation features sit in a multi-task policy's padded layout.

    Attributes:
        widths: the task's features per obs key, in key order.
        padded_widths: the policy's features per obs key (each at least the task's).
    """

    widths: tuple[int, ...]
    padded_widths: tuple[int, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "widths", tuple(int(width) for width in self.widths))
        object.__setattr__(self, "padded_widths", tuple(int(width) for width in self.padded_widths))
        if len(self.widths) != len(self.padded_widths):
            raise ValueError(
                f"obs widths {list(self.widths)} and padded widths {list(self.padded_widths)} differ in keys"
            )
        if any(width < 1 or width > padded for width, padded in zip(self.widths, self.padded_widths)):
            raise ValueError(f"obs widths {list(self.widths)} do not fit in padded widths {list(self.padded_widths)}")
        # Computed once: padding runs on every prediction of a multi-task policy.
        starts = np.concatenate([[0], np.cumsum(self.padded_widths)[:-1]])
        positions = [start + np.arange(width) for start, width in zip(starts, self.widths)]
        object.__setattr__(self, "_positions", np.concatenate(positions).astype(np.int64))

    @property
    def input_dim(self) -> int:
        """The task's own `Do`."""
        return sum(self.widths)

    @property
    def output_dim(self) -> int:
        """The policy's padded `Do`."""
        return sum(self.padded_widths)

    @property
    def pads(self) -> bool:
        """Whether any key is narrower than the padded layout."""
        return self.widths != self.padded_widths

    def positions(self) -> np.ndarray:
        """(input_dim,) int64: the padded column of each of the task's features."""
        return self._positions.copy()

    def matrix(self) -> np.ndarray:
        """(input_dim, output_dim) float32 0/1 matrix with `obs @ matrix` = the padded observations (exact)."""
        matrix = np.zeros((self.input_dim, self.output_dim), dtype=np.float32)
        matrix[np.arange(self.input_dim), self.positions()] = 1.0
        return matrix

    def pad(self, values: "np.ndarray | torch.Tensor") -> "np.ndarray | torch.Tensor":  # noqa: F821
        """(..., input_dim) -> (..., output_dim), zeros in the padded columns; keeps array type, dtype and device.

        Raises:
            ValueError: the last axis is not `input_dim` wide.
        """
        if values.shape[-1] != self.input_dim:
            raise ValueError(f"observations have {values.shape[-1]} features, this task has {self.input_dim}")
        if not self.pads:
            return values
        positions = self._positions
        if isinstance(values, np.ndarray):
            padded = np.zeros((*values.shape[:-1], self.output_dim), dtype=values.dtype)
        else:
            import torch

            positions = torch.as_tensor(positions, device=values.device)
            padded = values.new_zeros((*values.shape[:-1], self.output_dim))
        padded[..., positions] = values
        return padded

    def pad_normalizer(self, normalizer: MinMaxNormalizer) -> MinMaxNormalizer:
        """The task's statistics in the padded layout: each padded column a constant 0 (normalized to 0).

        Raises:
            ValueError: `normalizer` is not `input_dim` wide.
        """
        if normalizer.num_features != self.input_dim:
            raise ValueError(f"obs statistics have {normalizer.num_features} features, this task has {self.input_dim}")
        positions = self.positions()
        minimum, maximum = np.zeros(self.output_dim), np.zeros(self.output_dim)
        minimum[positions], maximum[positions] = normalizer.minimum, normalizer.maximum
        return MinMaxNormalizer(minimum=minimum, maximum=maximum)


def padded_layout(task_widths: Mapping[str, Sequence[int]]) -> dict[str, ObservationPadding]:
    """Each task's padding to the layout that gives every obs key its widest task's width.

    Args:
        task_widths: task -> its features per obs key, every task listing the same keys in the same order.

    Raises:
        ValueError: the tasks list different numbers of keys.
    """
    counts = {task: len(widths) for task, widths in task_widths.items()}
    if len(set(counts.values())) > 1:
        raise ValueError(f"the tasks observe different numbers of obs keys: {counts}")
    padded = tuple(int(max(column)) for column in zip(*task_widths.values()))
    return {task: ObservationPadding(tuple(widths), padded) for task, widths in task_widths.items()}
