"""Square's precision measure: how far off the peg's centre the nut is when it first touches the peg.

CARP's supplementary Tables 4-5 report, for nut assembly, the distance between the peg's insertion centre and the
nut's centre at their first contact. Here both centres are the points robosuite's own on-peg check compares
(`NutAssembly.on_peg`): the ``peg1`` body's position and the nut's root body's position, which is the centre of its
square hole (the four walls sit symmetrically around it; the handle shifts the centre of mass 11 mm off it, not the
body's origin). The distance is horizontal (x, y), in millimetres.

Deviations and consequences of robosuite's geometry:

- Contacts are looked at after every control step (25 physics steps of 2 ms at 20 Hz), so the offset is the one at the
  end of the control step in which the first contact happened. With the nut held in the gripper (the scripted
  expert, 12 episodes) that differs from the offset at the first physics step in contact by 0.2 mm on average and
  0.9 mm at most; a nut dropped freely onto the peg's edge tips, and moved up to 6 mm in that time in a 2 cm drop.
- The hole (45.5 mm across) is wider than the peg (32 mm across, 45.3 mm across its corners), so a nut whose centre
  comes within 6.75 mm of the peg's, turned to match it, slides down around the peg without touching it: robosuite
  counts it as on the peg, and it has no measure (NaN). Only the episodes whose nut touched the peg are measured.
"""

import numpy as np


class InsertionOffset:
    """Square: the nut's horizontal offset from the peg's centre at their first contact, in millimetres."""

    def __init__(self) -> None:
        self._nut_geoms = self._peg_geoms = np.zeros(0, dtype=bool)
        self._nut_body = self._peg_body = -1
        self._offset_mm = self._contact_step = float("nan")

    def reset(self, env) -> None:
        """Find the nut's and the peg's bodies and geoms (every reset of robosuite's env builds a new model)."""
        model = env.sim.model
        nut = env.nuts[env.nut_id]
        self._nut_body = env.obj_body_id[nut.name]
        self._peg_body = env.peg1_body_id  # the square peg; NutAssemblySquare only uses the square nut
        # Lookup tables over all geoms, so that a step's contacts are checked without a Python loop.
        self._nut_geoms = np.zeros(model.ngeom, dtype=bool)
        self._nut_geoms[env.obj_geom_id[nut.name]] = True
        self._peg_geoms = np.asarray(model.geom_bodyid) == self._peg_body
        self._offset_mm = self._contact_step = float("nan")

    def observe(self, env, step: int) -> None:
        """At the first step with a contact between a nut geom and a peg geom, record the offset and the step."""
        if not np.isnan(self._contact_step):
            return
        data = env.sim.data
        pairs = np.asarray(data.contact.geom[: data.ncon])  # (ncon, 2) geom ids of the active contacts
        nut_peg = self._nut_geoms[pairs[:, 0]] & self._peg_geoms[pairs[:, 1]]
        peg_nut = self._peg_geoms[pairs[:, 0]] & self._nut_geoms[pairs[:, 1]]
        if np.any(nut_peg | peg_nut):
            offset = data.body_xpos[self._nut_body][:2] - data.body_xpos[self._peg_body][:2]
            self._offset_mm = float(np.linalg.norm(offset) * 1000.0)
            self._contact_step = float(step)

    def values(self) -> dict[str, float]:
        """``insertion_offset_mm`` and ``insertion_contact_step`` (the 1-based control step), NaN without a contact."""
        return {"insertion_offset_mm": self._offset_mm, "insertion_contact_step": self._contact_step}
