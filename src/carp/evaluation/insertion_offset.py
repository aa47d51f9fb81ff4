"""The nut tasks' precision measure: how far off its peg's centre a nut is when it first touches the peg.

CARP's supplementary Tables 4-5 report, for nut assembly, the distance between the peg's insertion centre and the
nut's centre at their first contact. Here both centres are the points robosuite's own on-peg check compares
(`NutAssembly.on_peg`): the peg body's position (``peg1`` square, ``peg2`` round) and the nut's root body's
position, which is the centre of its hole (the square nut's four walls and the round nut's eight sit symmetrically
around it; the handle shifts the centre of mass off it, not the body's origin). The distance is horizontal (x, y), in
millimetres. Square has one nut and peg; NutAssembly has two pairs, each measured on its own.

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

import numpy as np


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


SQUARE_PAIRS = (NutOnPeg(0),)
"""NutAssemblySquare: the square nut on the square peg."""

NUT_ASSEMBLY_PAIRS = (NutOnPeg(0, "square_nut_"), NutOnPeg(1, "round_nut_"))
"""NutAssembly: each nut on its own peg, each measured apart."""


class InsertionOffset:
    """Each nut's horizontal offset from its peg's centre at their first contact, in millimetres.

    The episode's ``insertion_offset_mm`` is the mean over the pairs that touched (one pair: its offset) and its
    ``insertion_contact_step`` the first step any pair touched; a pair with a prefix also has its own two columns.

    Args:
        pairs: the nut and peg pairs to watch.
    """

    def __init__(self, pairs: tuple[NutOnPeg, ...] = SQUARE_PAIRS) -> None:
        if not pairs:
            raise ValueError("InsertionOffset needs at least one nut and peg pair")
        self.pairs = pairs
        self._nut_geoms = np.zeros((len(pairs), 0), dtype=bool)
        self._peg_geoms = np.zeros((len(pairs), 0), dtype=bool)
        self._nut_bodies = self._peg_bodies = np.zeros(len(pairs), dtype=np.int64)
        self._offsets_mm = np.full(len(pairs), np.nan)
        self._contact_steps = np.full(len(pairs), np.nan)

    def reset(self, env) -> None:
        """Find the nuts' and the pegs' bodies and geoms (every reset of robosuite's env builds a new model)."""
        model = env.sim.model
        peg_bodies = (env.peg1_body_id, env.peg2_body_id)
        geom_bodies = np.asarray(model.geom_bodyid)
        # Lookup tables over all geoms, (pairs, ngeom), so that a step's contacts are checked without a Python loop.
        self._nut_geoms = np.zeros((len(self.pairs), model.ngeom), dtype=bool)
        self._peg_geoms = np.zeros((len(self.pairs), model.ngeom), dtype=bool)
        nut_bodies, pegs = [], []
        for row, pair in enumerate(self.pairs):
            nut = env.nuts[pair.nut]
            nut_bodies.append(env.obj_body_id[nut.name])
            pegs.append(peg_bodies[pair.nut])
            self._nut_geoms[row, env.obj_geom_id[nut.name]] = True
            self._peg_geoms[row] = geom_bodies == pegs[-1]
        self._nut_bodies, self._peg_bodies = np.array(nut_bodies), np.array(pegs)
        self._offsets_mm = np.full(len(self.pairs), np.nan)
        self._contact_steps = np.full(len(self.pairs), np.nan)

    def observe(self, env, step: int) -> None:
        """At each pair's first step with a contact between its nut's and its peg's geoms, record offset and step."""
        waiting = np.isnan(self._contact_steps)
        if not waiting.any():
            return
        data = env.sim.data
        pairs = np.asarray(data.contact.geom[: data.ncon])  # (ncon, 2) geom ids of the active contacts
        first, second = pairs[:, 0], pairs[:, 1]
        nut_peg = self._nut_geoms[:, first] & self._peg_geoms[:, second]  # (pairs, ncon)
        peg_nut = self._peg_geoms[:, first] & self._nut_geoms[:, second]
        touching = np.any(nut_peg | peg_nut, axis=1) & waiting
        for row in np.flatnonzero(touching):
            offset = data.body_xpos[self._nut_bodies[row]][:2] - data.body_xpos[self._peg_bodies[row]][:2]
            self._offsets_mm[row] = float(np.linalg.norm(offset) * 1000.0)
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
