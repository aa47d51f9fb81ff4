"""The served policy: where it came from, one lock around it, and its warm-up check against the serving spec."""

import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from carp.data.sources import file_sha256
from carp.policies.base import TORCH_BACKEND, Policy, TimedPrediction
from carp.serving.session import IMAGES_KEY, Observed, ServingSpec

__all__ = ["ModelSource", "ServedModel", "file_sha256"]

CONCURRENT_BACKENDS = ("onnxruntime",)
"""Backends whose policy may predict for several requests at once from several threads: an ONNX Runtime session's
`run` is thread-safe, and each call gets its own inputs and its episode's own generator."""


@dataclass(frozen=True)
class ModelSource:
    """Where the served checkpoint came from.

    Attributes:
        path: the checkpoint file, or the registry URI (``models:/<name>@<alias>``) it was resolved from.
        sha256: hex sha256 of the checkpoint's bytes.
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
    """A loaded policy shared by every connection; predictions in PyTorch take turns under one lock.

    One lock because a PyTorch policy's modules are not written for concurrent calls (the server predicts with it on
    one thread at a time; the lock keeps any other caller, such as a warm-up, out of its way). Exported graphs
    (`concurrent`) predict without it.

    Attributes:
        policy: the policy, with its inference settings applied.
        source: where its checkpoint came from.
        inference: the settings given to its `configure_inference`, reported in the metadata.
        backend: what runs the predictions (`torch`, or `onnxruntime` for exported graphs), reported in the metadata.
        task: the task served (a multi-task policy serves the one selected at startup), reported in the metadata.
    """

    policy: Policy
    source: ModelSource
    inference: dict[str, Any] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)
    backend: str = TORCH_BACKEND
    task: str = ""

    def predict(self, observed: Observed) -> tuple[TimedPrediction, float]:
        """Predict one chunk; returns the prediction and the seconds spent waiting for the lock.

        Args:
            observed: (To, Do) float32 observation history, (To, cameras, 3, h, w) uint8 images or None, and the
                episode's generator.

        Returns:
            The policy's prediction, whose `actions` are (1, H, A) float32, and the lock wait in seconds.
        """
        seen = {} if observed.image_history is None else {IMAGES_KEY: observed.image_history[None]}
        if self.concurrent:
            return self.policy.predict_action_timed(observed.obs_history[None], generator=observed.generator), 0.0
        waiting = time.perf_counter()
        with self.lock:
            waited = time.perf_counter() - waiting
            timed = self.policy.predict_action_timed(observed.obs_history[None], generator=observed.generator, **seen)
        return timed, waited

    @property
    def concurrent(self) -> bool:
        """Whether several threads may predict at once (`CONCURRENT_BACKENDS`), one request each."""
        return self.backend in CONCURRENT_BACKENDS

    @property
    def batches(self) -> bool:
        """Whether requests of several episodes may share one call: in PyTorch, for a policy that draws nothing.

        Exported graphs (`onnxruntime`) take one environment per call.
        """
        return self.backend == TORCH_BACKEND and not self.policy.draws_random

    def predict_batch(self, batch: list[Observed]) -> tuple[TimedPrediction, float]:
        """Predict one chunk per observation history of `batch` in one call (a policy that draws nothing, `batches`).

        Each row is what the policy predicts for that history alone, up to the last bits of float arithmetic (a
        batched matrix product may sum in another order than a single row's).

        Args:
            batch: B observations, each (To, Do) float32 and (To, cameras, 3, h, w) uint8 images or None.

        Returns:
            The prediction, whose `actions` are (B, H, A) float32, and the lock wait in seconds.
        """
        obs = np.stack([observed.obs_history for observed in batch])  # (B, To, Do)
        seen = {}
        if batch[0].image_history is not None:
            seen[IMAGES_KEY] = np.stack([observed.image_history for observed in batch])  # (B, To, cameras, 3, h, w)
        waiting = time.perf_counter()
        with self.lock:
            waited = time.perf_counter() - waiting
            timed = self.policy.predict_action_timed(obs, **seen)
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
