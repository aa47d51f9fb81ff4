"""Nested demo subsets: a smaller subset is part of every larger one, the same for every caller."""

import pytest

from carp.data.subsets import nested_subset

NAMES = [f"demo_{index}" for index in range(200)]


def test_smaller_subsets_are_contained_in_larger_ones_and_keep_file_order():
    subsets = {size: nested_subset(NAMES, size, seed=0) for size in (30, 60, 100, 200)}
    assert [len(subset) for subset in subsets.values()] == [30, 60, 100, 200]
    assert set(subsets[30]) < set(subsets[60]) < set(subsets[100]) < set(subsets[200]) == set(NAMES)
    for subset in subsets.values():
        assert subset == sorted(subset, key=NAMES.index)


def test_the_subset_depends_on_the_seed_only():
    assert nested_subset(NAMES, 30, seed=0) == nested_subset(list(NAMES), 30, seed=0)
    assert nested_subset(NAMES, 30, seed=0) != nested_subset(NAMES, 30, seed=1)
    # Not simply the first demos of the file: the shuffle spreads the subset over the whole collection.
    assert max(NAMES.index(name) for name in nested_subset(NAMES, 30, seed=0)) > 100


@pytest.mark.parametrize("size", [0, 201])
def test_a_size_outside_the_file_is_refused(size):
    with pytest.raises(ValueError, match=rf"a subset of {size} demos needs 1 <= size <= 200"):
        nested_subset(NAMES, size, seed=0)
