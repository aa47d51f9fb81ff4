"""The insertion tasks' precision measure: how far off its target's centre a tool is when it first touches the target.

CARP's supplementary Tables 4-5 report, for nut assembly, the distance between the peg's insertion centre and the
nut's centre at their first contact. The same measure serves every task that inserts one thing into another: a pair
(`InsertionPair`) names the tool's and the target's geoms and the offset between their centres, measured in the plane
across the insertion's axis; `InsertionOffset` watches the simulator's contacts and records each pair's offset at its
first contact, in millimetres.

- Square and NutAssembly (`NutOnPeg`, here): the centres are the points robosuite's own on-peg check compares
  (`NutAssembly.on_peg`): the peg body's position (``peg1`` square, ``peg2`` round) and the nut's root body's
  position, which is the centre of its hole (the square nut's four walls and the round nut's eight sit symmetrically
  around it; the handle shifts the centre of mass off it, not the body's origin). The pegs stand upright, so the
  plane is the horizontal one and the distance is in x and y. Square has one nut and peg; NutAssembly has two pairs,
  each measured on its own.
- Threading (`carp.tasks.threading.insertion.NeedleInRing`): the ring's centre, and the point where the needle's axis
  meets the ring's mid-plane.

Deviations and consequences of robosuite's geometry:

- Contacts are looked at after every control step (25 physics steps of 2 ms at 20 Hz), so the offset is the one at the
  end of the control step in which the first contact happened. With the nut held in the gripper (the scripted
  expert, 12 episodes) that differs from the offset at the first physics step in contact by 0.2 mm on average and
  0.9 mm at most; a nut dropped freely onto the peg's edge tips, and moved up to 6 mm in that time in a 2 cm drop.
- The hole (45.5 mm across) is wider than the peg (32 mm across, 45.3 mm across its corners), so a nut whose centre
  comes within 6.75 mm of the peg's, turned to match it, slides down around the peg without touching it: robosuite
  counts it as on the peg, and it has no measure (NaN). Only the episodes whose nut touched the peg are measured.
  The round nut's hole (62.4 mm across its flats) leaves 11.2 mm of room around its peg (40 mm across).
"""

from dataclasses import dataclass
from typing import Protocol

import numpy as np


class InsertionPair(Protocol):
    """A tool and the target it goes into.

    Attributes:
        prefix: prefix of this pair's own columns (e.g. ``square_nut_``); empty for a task with one pair, whose
            offset is the episode's.
    """

    prefix: str

    def geoms(self, env) -> tuple[np.ndarray, np.ndarray]:
        """The tool's and the target's geom ids (1-D int arrays) in the env's current model."""
        ...

    def offset_m(self, env) -> float:
        """The distance (m) between the target's centre and the tool's, in the plane across the insertion's axis."""
        ...


@dataclass(frozen=True)
class NutOnPeg:
    """One nut and the peg it goes on, in robosuite's NutAssembly numbering.

    Attributes:
        nut: index into the env's ``nuts`` (0 the square nut, 1 the round one); robosuite puts nut i on peg ``i + 1``
            (``peg1`` square, ``peg2`` round), as its on-peg check does.
        prefix: prefix of this pair's own columns (e.g. ``square_nut_``); empty for a task with one pair, whose
            offset is the episode's.
    """

    nut: int
    prefix: str = ""

    def _bodies(self, env) -> tuple[int, int]:
        return env.obj_body_id[env.nuts[self.nut].name], (env.peg1_body_id, env.peg2_body_id)[self.nut]

    def geoms(self, env) -> tuple[np.ndarray, np.ndarray]:
        """The nut's geoms and the peg body's."""
        _, peg = self._bodies(env)
        nut_geoms = np.asarray(env.obj_geom_id[env.nuts[self.nut].name])
        return nut_geoms, np.flatnonzero(np.asarray(env.sim.model.geom_bodyid) == peg)

    def offset_m(self, env) -> float:
        """Horizontal (x, y) distance between the nut's root body and the peg's body."""
        nut, peg = self._bodies(env)
        positions = env.sim.data.body_xpos
        return float(np.linalg.norm(positions[nut][:2] - positions[peg][:2]))


class InsertionOffset:
    """Each tool's offset from its target's centre at their first contact, in millimetres.

    The episode's ``insertion_offset_mm`` is the mean over the pairs that touched (one pair: its offset) and its
    ``insertion_contact_step`` the first step any pair touched; a pair with a prefix also has its own two columns.

    Args:
        pairs: the tool and target pairs to watch (each task's, e.g. `carp.tasks.square.task.SQUARE_PAIRS`).
    """

    def __init__(self, pairs: tuple[InsertionPair, ...]) -> None:
        if not pairs:
            raise ValueError("InsertionOffset needs at least one tool and target pair")
        self.pairs = pairs
        self._tool_geoms = np.zeros((len(pairs), 0), dtype=bool)
        self._target_geoms = np.zeros((len(pairs), 0), dtype=bool)
        self._offsets_mm = np.full(len(pairs), np.nan)
        self._contact_steps = np.full(len(pairs), np.nan)

    def reset(self, env) -> None:
        """Find each pair's geoms (every reset of robosuite's env builds a new model)."""
        ngeom = env.sim.model.ngeom
        # Lookup tables over all geoms, (pairs, ngeom), so that a step's contacts are checked without a Python loop.
        self._tool_geoms = np.zeros((len(self.pairs), ngeom), dtype=bool)
        self._target_geoms = np.zeros((len(self.pairs), ngeom), dtype=bool)
        for row, pair in enumerate(self.pairs):
            tool, target = pair.geoms(env)
            self._tool_geoms[row, tool] = True
            self._target_geoms[row, target] = True
        self._offsets_mm = np.full(len(self.pairs), np.nan)
        self._contact_steps = np.full(len(self.pairs), np.nan)

    def observe(self, env, step: int) -> None:
        """At each pair's first step with a contact between its tool's and target's geoms, record offset and step."""
        waiting = np.isnan(self._contact_steps)
        if not waiting.any():
            return
        data = env.sim.data
        contacts = np.asarray(data.contact.geom[: data.ncon])  # (ncon, 2) geom ids of the active contacts
        first, second = contacts[:, 0], contacts[:, 1]
        tool_target = self._tool_geoms[:, first] & self._target_geoms[:, second]  # (pairs, ncon)
        target_tool = self._target_geoms[:, first] & self._tool_geoms[:, second]
        touching = np.any(tool_target | target_tool, axis=1) & waiting
        for row in np.flatnonzero(touching):
            self._offsets_mm[row] = self.pairs[row].offset_m(env) * 1000.0
            self._contact_steps[row] = float(step)

    def values(self) -> dict[str, float]:
        """The episode's ``insertion_offset_mm`` and ``insertion_contact_step`` (1-based), and each prefixed pair's.

        NaN where no contact happened.
        """
        touched = np.isfinite(self._offsets_mm)
        values = {
            "insertion_offset_mm": float(np.mean(self._offsets_mm[touched])) if touched.any() else float("nan"),
            "insertion_contact_step": float(np.min(self._contact_steps[touched])) if touched.any() else float("nan"),
        }
        for row, pair in enumerate(self.pairs):
            if pair.prefix:
                values[f"{pair.prefix}insertion_offset_mm"] = float(self._offsets_mm[row])
                values[f"{pair.prefix}insertion_contact_step"] = float(self._contact_steps[row])
        return values
