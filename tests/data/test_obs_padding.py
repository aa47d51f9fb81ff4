"""Observation padding of a multi-task policy: per-key placement, numpy and torch alike, statistics, the matrix."""

import numpy as np
import pytest
import torch

from carp.data.normalizer import MinMaxNormalizer
from carp.data.obs_padding import ObservationPadding, padded_layout


def test_each_key_gets_its_widest_task_width_and_a_task_fills_the_first_columns():
    layout = padded_layout({"lift": (10, 3, 4, 2), "can": (14, 3, 4, 2), "stack": (23, 3, 4, 2)})
    assert {task: padding.padded_widths for task, padding in layout.items()} == {
        task: (23, 3, 4, 2) for task in ("lift", "can", "stack")
    }
    lift = layout["lift"]
    assert (lift.input_dim, lift.output_dim, lift.pads) == (19, 32, True)
    np.testing.assert_array_equal(lift.positions(), [*range(10), *range(23, 32)])
    assert not layout["stack"].pads


def test_padding_places_features_and_zeros_alike_in_numpy_torch_and_the_matrix():
    padding = ObservationPadding(widths=(2, 1), padded_widths=(3, 2))
    obs = np.arange(1, 2 * 4 * 3 + 1, dtype=np.float32).reshape(2, 4, 3)  # (B, To, Do_task)
    padded = padding.pad(obs)
    assert padded.shape == (2, 4, 5) and padded.dtype == np.float32
    np.testing.assert_array_equal(padded[..., [0, 1, 3]], obs)
    np.testing.assert_array_equal(padded[..., [2, 4]], 0.0)
    np.testing.assert_array_equal(padding.pad(torch.as_tensor(obs)).numpy(), padded)
    np.testing.assert_array_equal(obs @ padding.matrix(), padded)  # exact: one 1 per column
    unpadded = ObservationPadding(widths=(2, 1), padded_widths=(2, 1))
    assert unpadded.pad(obs) is obs


def test_padded_statistics_normalize_a_padded_column_to_zero_and_keep_the_others():
    padding = ObservationPadding(widths=(2, 1), padded_widths=(3, 2))
    normalizer = MinMaxNormalizer(np.array([0.0, -2.0, 10.0]), np.array([4.0, 2.0, 20.0]))
    padded_normalizer = padding.pad_normalizer(normalizer)
    obs = np.array([[1.0, 0.5, 12.0], [3.0, -1.0, 20.0]])
    np.testing.assert_allclose(
        padded_normalizer.normalize(padding.pad(obs)), padding.pad(normalizer.normalize(obs)), atol=1e-12
    )
    np.testing.assert_array_equal(padded_normalizer.normalize(padding.pad(obs))[:, [2, 4]], 0.0)


def test_wrong_widths_are_refused_with_the_numbers():
    with pytest.raises(ValueError, match=r"obs widths \[4, 1\] do not fit in padded widths \[3, 2\]"):
        ObservationPadding(widths=(4, 1), padded_widths=(3, 2))
    padding = ObservationPadding(widths=(2, 1), padded_widths=(3, 2))
    with pytest.raises(ValueError, match="observations have 5 features, this task has 3"):
        padding.pad(np.zeros((1, 5)))
    with pytest.raises(ValueError, match="different numbers of obs keys"):
        padded_layout({"lift": (10, 3), "can": (14,)})
