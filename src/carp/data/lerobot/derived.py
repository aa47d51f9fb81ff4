"""Observations a task derives from other features of a LeRobotDataset: the seam between the reader and a task.

A task whose observation keys a published dataset lacks, but whose values follow from features it has, offers a
:class:`FeatureAdapter` (Push-T: DP's block keypoints from ``lerobot/pusht_keypoints``' polygon vertices). The reader
(:func:`carp.data.lerobot.reader.read_lerobot_demonstrations`) uses it only when some of the task's keys are missing:
it checks that the adapter's source features exist with their widths, reads them like any feature, and hands each
episode's values to :meth:`FeatureAdapter.derive`, whose observations (and simulator states) replace the missing
keys. A dataset that already holds the task's keys (carp's own export) is read as it is.
"""

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class DerivedFeatures:
    """What an adapter derives from one episode.

    Attributes:
        obs: each key of :attr:`FeatureAdapter.provides` -> (T, D_key) float64.
        states: (T, S) float64 simulator states the task resets to, or None when the features do not determine them.
    """

    obs: dict[str, np.ndarray]
    states: np.ndarray | None = None


class FeatureAdapter(Protocol):
    """Derives a task's observation keys from other features of a LeRobotDataset.

    Attributes:
        provides: the obs keys it derives; it is used when one of them names no feature of the dataset.
        sources: feature name -> width D of the 1-D features it reads, (T, D) each.
        layout: the dataset layout it reads, in words, for the one-line refusal of a dataset without its sources
            (e.g. ``lerobot/pusht_keypoints: observation.environment_state (16) and observation.state (2)``).
    """

    provides: tuple[str, ...]
    sources: Mapping[str, int]
    layout: str

    def derive(self, values: Mapping[str, np.ndarray], where: str) -> DerivedFeatures:
        """The derived observations of one episode.

        Args:
            values: each feature of :attr:`sources` -> (T, D) float64, as stored.
            where: ``<data file>: episode <index>``, the start of any error message.

        Raises:
            DatasetError: one line starting with ``where`` naming the frame and the problem.
        """
        ...
