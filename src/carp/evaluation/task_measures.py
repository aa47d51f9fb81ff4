"""Per-episode measures a task adds to its evaluation, asked of the task and never of its name elsewhere.

A measure watches one episode through the env: `reset` after the episode's reset, `observe` after every control
step, and `values` at the end (name -> float, NaN for "not measured in this episode"). The registry maps a task name
(a key of `carp.simulation.TASK_ENV_NAMES`) to the class of its measure, one line per task; a task without one gets
`NoMeasure`, which adds no columns and no work per step. Each measure lives in its own module
(Square: `carp.evaluation.insertion_offset`).
"""

from collections.abc import Callable
from typing import Protocol

from carp.evaluation.insertion_offset import InsertionOffset


class EpisodeMeasure(Protocol):
    """What the rollout asks of a task's measure."""

    def reset(self, env) -> None:
        """Start a new episode in `env` (after its reset)."""
        ...

    def observe(self, env, step: int) -> None:
        """Look at `env` after control step `step` (1-based)."""
        ...

    def values(self) -> dict[str, float]:
        """The episode's measures by name; NaN where the episode gave none."""
        ...


class NoMeasure:
    """The measure of a task that has none."""

    def reset(self, env) -> None:
        """Nothing to prepare."""

    def observe(self, env, step: int) -> None:
        """Nothing to watch."""

    def values(self) -> dict[str, float]:
        """No values."""
        return {}


MEASURES: dict[str, Callable[[], EpisodeMeasure]] = {"square": InsertionOffset}
"""Task name -> a factory of its measure."""


def measure_for(task: str | None) -> EpisodeMeasure:
    """A fresh measure for one episode of `task` (`NoMeasure` for a task without one, or for None)."""
    factory = MEASURES[task] if task in MEASURES else NoMeasure
    return factory()
