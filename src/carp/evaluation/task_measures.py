"""Per-episode measures a task adds to its evaluation, asked of the task and never of its name elsewhere.

A measure watches an episode through the env (`reset` after the episode's reset, `observe` after every step) and
gives its values at the end (`values`: name -> float, NaN for "not measured in this episode"). The registry maps a
robosuite env class to its measure; tasks without one get `NoMeasure`, which costs nothing per step.

Square's `InsertionOffset` is the precision measure of CARP's supplementary Tables 4-5: at the first contact between
the nut and the peg it must go on, the horizontal distance between the nut's centre and the peg's. robosuite's own
on-peg check compares the same two points (the nut body's position, the centre of its hole, with the peg body's), so
an offset of 0 is a nut centred on its peg.
"""

from collections.abc import Callable
from typing import Protocol

import numpy as np


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


class InsertionOffset:
    """Square: the nut's horizontal offset from the peg's centre at their first contact, in millimetres."""

    def __init__(self) -> None:
        self._nut_geoms: set[int] = set()
        self._peg_geoms: set[int] = set()
        self._nut_body = self._peg_body = -1
        self._offset_mm = self._contact_step = float("nan")

    def reset(self, env) -> None:
        """Find the active nut's geoms and body and the square peg's (each reset builds a new model)."""
        model = env.sim.model
        nut = env.nuts[env.nut_id]
        self._nut_body = env.obj_body_id[nut.name]
        self._nut_geoms = set(env.obj_geom_id[nut.name])
        self._peg_body = env.peg1_body_id
        self._peg_geoms = set(np.flatnonzero(np.asarray(model.geom_bodyid) == self._peg_body).tolist())
        self._offset_mm = self._contact_step = float("nan")

    def observe(self, env, step: int) -> None:
        """Record the offset at the first step whose contacts include a nut geom touching a peg geom."""
        if not np.isnan(self._contact_step):
            return
        data = env.sim.data
        for contact in data.contact[: data.ncon]:
            pair = {int(contact.geom1), int(contact.geom2)}
            if pair & self._nut_geoms and pair & self._peg_geoms:
                offset = data.body_xpos[self._nut_body][:2] - data.body_xpos[self._peg_body][:2]
                self._offset_mm = float(np.linalg.norm(offset) * 1000.0)
                self._contact_step = float(step)
                return

    def values(self) -> dict[str, float]:
        """``insertion_offset_mm`` and ``insertion_contact_step`` (both NaN without a contact)."""
        return {"insertion_offset_mm": self._offset_mm, "insertion_contact_step": self._contact_step}


MEASURES: dict[str, Callable[[], EpisodeMeasure]] = {"NutAssemblySquare": InsertionOffset}
"""robosuite env class name -> its task's measure."""


def measure_for(env) -> EpisodeMeasure:
    """A fresh measure for the task `env` runs (`NoMeasure` for a task without one)."""
    return MEASURES.get(type(env).__name__, NoMeasure)()
