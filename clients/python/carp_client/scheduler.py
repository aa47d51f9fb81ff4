"""`ChunkScheduler`: from action chunks to one action per control step, on the robot's side.

Time convention (carp's docs/architecture.md, "Time convention"): a chunk predicted from the observations up to control
step t is (H, A); its row ``To - 1`` (the metadata's ``executed_offset``) acts at step t, row ``To - 1 + i`` at step
t + i. Every action is stamped with the step it belongs to, so a chunk that arrives late (the robot went on meanwhile)
loses only its rows for steps already executed, and a step is never given an action meant for another.

Two ways of using the chunks:

- Plain (the default), as carp's evaluation runs a policy: a chunk covers ``Ta`` steps (the metadata's
  ``action_steps``) and the robot asks for the next chunk when they run out. Where two chunks cover a step, the one
  predicted last wins.
- Temporal ensembling, as ACT (Zhao et al., 2023, "Learning Fine-Grained Bimanual Manipulation with Low-Cost
  Hardware", section 3.3) does when it queries the policy at every step: a chunk covers every step from its row
  ``To - 1`` to its last row (``H - To + 1`` steps), and a step's action is the weighted mean of the rows every
  chunk covering it predicts for it, weight ``exp(-m * i)`` for the i-th oldest prediction (i = 0 the oldest),
  normalized to sum to one. ``m = 0`` is the plain mean; a larger ``m`` trusts older predictions more, as ACT's
  ``k`` does. Deviation from ACT: a chunk's rows before ``To - 1`` are never used (they belong to steps already
  past when it was predicted; ACT conditions on one observation step, so its whole chunk lies ahead).

Pure numpy; nothing here talks to the server.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def ensemble_weights(count: int, m: float) -> np.ndarray:
    """(count,) float64 weights of `count` predictions of one step, oldest first: ``exp(-m * i)`` normalized."""
    weights = np.exp(-m * np.arange(count, dtype=np.float64))
    return weights / weights.sum()


class ChunkScheduler:
    """Keeps the actions of received chunks by the control step they belong to.

    Args:
        executed_offset: ``To - 1``, the row of a chunk that acts at the step it was predicted at.
        action_steps: ``Ta``, steps a chunk covers without ensembling.
        ensemble_m: None for plain execution; a number >= 0 for temporal ensembling with weights
            ``exp(-ensemble_m * i)`` (see the module docstring).
    """

    def __init__(self, executed_offset: int, action_steps: int, ensemble_m: float | None = None) -> None:
        if executed_offset < 0 or action_steps < 1:
            raise ValueError(f"need executed_offset >= 0 and action_steps >= 1, got {executed_offset}, {action_steps}")
        if ensemble_m is not None and not ensemble_m >= 0:
            raise ValueError(f"ensemble_m must be >= 0 (or None for no ensembling), got {ensemble_m}")
        self.executed_offset = executed_offset
        self.action_steps = action_steps
        self.ensemble_m = ensemble_m
        self._rows: dict[int, list[tuple[int, np.ndarray]]] = {}
        self._next_step = 0

    @classmethod
    def from_metadata(cls, metadata: dict[str, Any], ensemble_m: float | None = None) -> ChunkScheduler:
        """A scheduler for the server whose metadata frame is `metadata` (`PolicyClient.metadata`)."""
        return cls(int(metadata["executed_offset"]), int(metadata["action_steps"]), ensemble_m)

    def reset(self) -> None:
        """Forget every chunk: a new episode starts at step 0."""
        self._rows.clear()
        self._next_step = 0

    def add(self, chunk: np.ndarray, step: int) -> int:
        """Take the chunk predicted from the observation at control step `step`.

        Args:
            chunk: (H, A) actions, as the server's reply holds them.
            step: the control step of the observation it was predicted from.

        Returns:
            The rows kept: those of steps not yet executed (the others are stale and dropped).

        Raises:
            ValueError: a chunk too short for the offset and the steps it must cover.
        """
        chunk = np.asarray(chunk)
        if chunk.ndim != 2:
            raise ValueError(f"chunk: expected (H, A), got shape {chunk.shape}")
        covered = chunk.shape[0] - self.executed_offset if self.ensemble_m is not None else self.action_steps
        if covered < 1 or self.executed_offset + covered > chunk.shape[0]:
            raise ValueError(
                f"chunk: {chunk.shape[0]} rows cannot cover {covered} steps from row {self.executed_offset}"
            )
        kept = 0
        for index in range(covered):
            if step + index < self._next_step:
                continue
            self._rows.setdefault(step + index, []).append((step, chunk[self.executed_offset + index]))
            kept += 1
        return kept

    def has_action(self, step: int) -> bool:
        """Whether a received chunk covers control step `step` (else the robot must ask for one)."""
        return step >= self._next_step and step in self._rows

    def action(self, step: int) -> np.ndarray | None:
        """The action to execute at control step `step`, or None when no received chunk covers it.

        Marks `step` as executed: actions of earlier steps, and later-arriving rows for it, are dropped.

        Returns:
            (A,) in the chunks' dtype: the newest prediction's row, or the ensembled mean.

        Raises:
            ValueError: `step` comes before a step already executed.
        """
        if step < self._next_step:
            raise ValueError(f"step {step} comes before step {self._next_step - 1}, which was already executed")
        for stale in [past for past in self._rows if past < step]:
            del self._rows[stale]
        self._next_step = step + 1
        predictions = sorted(self._rows.pop(step, []), key=lambda prediction: prediction[0])
        if not predictions:
            return None
        if self.ensemble_m is None:
            return predictions[-1][1].copy()
        rows = np.stack([row for _, row in predictions]).astype(np.float64)  # (count, A)
        mean = ensemble_weights(len(predictions), self.ensemble_m) @ rows
        return mean.astype(predictions[0][1].dtype)
