"""The served policy: where it came from, one lock around it, and its warm-up check against the serving spec."""

import hashlib
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from carp.policies.base import Policy, TimedPrediction
from carp.serving.session import IMAGES_KEY, Observed, ServingSpec


def file_sha256(path: Path) -> str:
    """Hex sha256 of the file at `path`, read in chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


@dataclass(frozen=True)
class ModelSource:
    """Where the served checkpoint came from.

    Attributes:
        path: the checkpoint file.
        sha256: hex sha256 of its bytes.
        name: registered model name when loaded from a model registry; None for a file.
        version: registered model version; None for a file.
        alias: registry alias the version was resolved from; None for a file.
    """

    path: str
    sha256: str
    name: str | None = None
    version: str | None = None
    alias: str | None = None

    @property
    def model_version(self) -> str:
        """What each reply names as its model: the registry version, else the checkpoint's sha256 prefix."""
        return self.version if self.version is not None else self.sha256[:12]


@dataclass
class ServedModel:
    """A loaded policy shared by every connection; predictions take turns under one lock.

    One lock because a policy's modules are not written for concurrent calls; the server runs predictions on a thread
    pool, so the lock is what serializes them (batching across robots is left for later).

    Attributes:
        policy: the policy, with its inference settings applied.
        source: where its checkpoint came from.
        inference: the settings given to its `configure_inference`, reported in the metadata.
    """

    policy: Policy
    source: ModelSource
    inference: dict[str, Any] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def predict(self, observed: Observed) -> tuple[TimedPrediction, float]:
        """Predict one chunk; returns the prediction and the seconds spent waiting for the lock.

        Args:
            observed: (To, Do) float32 observation history, (To, cameras, 3, h, w) uint8 images or None, and the
                episode's generator.

        Returns:
            The policy's prediction, whose `actions` are (1, H, A) float32, and the lock wait in seconds.
        """
        seen = {} if observed.image_history is None else {IMAGES_KEY: observed.image_history[None]}
        waiting = time.perf_counter()
        with self.lock:
            waited = time.perf_counter() - waiting
            timed = self.policy.predict_action_timed(observed.obs_history[None], generator=observed.generator, **seen)
        return timed, waited

    def warm_up(self, spec: ServingSpec) -> None:
        """Run one prediction on zero observations and check the chunk's shape against `spec`.

        The first call pays one-time costs (allocations, kernel selection) that should not fall on a robot's first
        request. Its draws come from a throwaway generator, so no episode's draws are affected.

        Raises:
            ValueError: the policy predicts another (H, A) than `spec` declares.
        """
        images = None if spec.image_shape is None else np.zeros((spec.obs_steps, *spec.image_shape), np.uint8)
        observed = Observed(np.zeros((spec.obs_steps, spec.obs_dim), np.float32), images, torch.Generator())
        timed, _ = self.predict(observed)
        expected = (1, spec.action_horizon, spec.action_dim)
        if tuple(timed.actions.shape) != expected:
            raise ValueError(
                f"{self.source.path}: the policy predicts chunks of shape {tuple(timed.actions.shape)[1:]}, "
                f"the serving spec declares (H, A) = {expected[1:]}"
            )
