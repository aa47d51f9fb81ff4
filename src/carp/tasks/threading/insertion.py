"""Threading's insertion pair for `carp.tasks.arms.insertion_offset.InsertionOffset`: the needle through the ring.

The centres are the ring's centre and the point where the needle's axis (through the bar, from the handle to the tip)
meets the ring's mid-plane; the plane is the ring's, upright, across its horizontal axis. A needle at first contact is
usually still in front of the ring, and its axis extended to the plane is where it would pass; a needle lying within 6
degrees of the ring's plane meets it nowhere near the ring, and is measured by its tip's distance from the ring's axis
instead.

The ring (40 mm across inside) leaves 16 mm of room around the needle's bar (8 mm across): a needle that passes within
16 mm of the ring's centre, along its axis, never touches it and has no measure.
"""

from dataclasses import dataclass

import numpy as np

NEEDLE_IN_RING_PLANE_COSINE = 0.1
"""Below this cosine between the needle and the ring's axis (about 84 degrees) the needle is measured by its tip."""


@dataclass(frozen=True)
class NeedleInRing:
    """Threading's needle and ring (`carp.tasks.threading.env`); contacts with the tripod's legs do not count.

    Attributes:
        prefix: as `carp.tasks.arms.insertion_offset.InsertionPair`'s.
    """

    prefix: str = ""

    def geoms(self, env) -> tuple[np.ndarray, np.ndarray]:
        """The needle's handle and bar, and the ring's segments."""
        return np.asarray(env.needle_geom_ids), np.asarray(env.ring_geom_ids)

    def offset_m(self, env) -> float:
        """Distance from the ring's centre to where the needle's axis meets the ring's mid-plane (module docstring)."""
        center, axis = env.ring_center(), env.ring_axis()
        tip, needle = env.needle_tip(), env.needle_axis()
        tip_depth = float(np.dot(tip - center, axis))
        cosine = float(np.dot(needle, axis))
        if abs(cosine) < NEEDLE_IN_RING_PLANE_COSINE:
            return float(np.linalg.norm(tip - center - tip_depth * axis))
        crossing = tip - needle * (tip_depth / cosine)
        return float(np.linalg.norm(crossing - center))


THREADING_PAIRS = (NeedleInRing(),)
"""Threading: the needle through the ring."""
