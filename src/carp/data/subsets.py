"""Nested demo subsets for data-efficiency studies.

robomimic's way: one seeded shuffle of a file's demos, and a subset of size n is the first n demos of that order, so
a smaller subset is always contained in a larger one (the prefix property) and every policy family trained from the
same file and seed sees the same demos. The order depends only on the file's demo names and the seed; the chosen
demos keep their file order.
"""

from collections.abc import Sequence

import numpy as np


def nested_subset(names: Sequence[str], size: int, seed: int) -> list[str]:
    """The first `size` demos of `names` in the order a `seed`-ed shuffle gives, returned in file order.

    Args:
        names: the file's demo names in file order.
        size: demos to keep; 1 <= size <= len(names).
        seed: the shuffle's seed.

    Raises:
        ValueError: `size` is outside [1, len(names)].
    """
    if not 1 <= size <= len(names):
        raise ValueError(f"a subset of {size} demos needs 1 <= size <= {len(names)}, the demos available")
    order = np.random.default_rng(seed).permutation(len(names))
    kept = set(order[:size].tolist())
    return [name for index, name in enumerate(names) if index in kept]
