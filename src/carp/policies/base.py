"""What every policy family offers the rest of carp: the `Policy` protocol and the checkpoint envelope.

Training, evaluation and reporting talk to a policy only through this protocol, so a new family is a folder under
`carp.policies` plus one line in `carp.policies.registry`; nothing outside the family's folder names its classes.

A checkpoint is one self-contained file: a dict with `format_version`, `policy_type` (the registry name of the
family that wrote it) and the family's own entries. `carp.policies.registry.load_policy` reads the two envelope
entries and hands the rest to the family's loader.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol, runtime_checkable

# Annotations only: the params loader reaches this module through the registry, and reading params should not pay
# for importing torch.
if TYPE_CHECKING:
    import numpy as np
    import torch

POLICY_FORMAT_VERSION = 3
"""Version 3 added `policy_type`; version 2 checkpoints held a CARP policy without it."""

TORCH_BACKEND = "torch"


class TimedPrediction(NamedTuple):
    """Actions of one call and where its time went.

    Attributes:
        actions: (B, H, A) float32 raw actions.
        prediction_seconds: everything up to the family's decoding step (for CARP: normalization and the K
            coarse-to-fine steps; for a diffusion policy: the whole denoising loop).
        decoding_seconds: turning the prediction into raw actions (CARP: tokenizer decoding and un-normalization);
            only the un-normalization for families without a decoder.
        model_calls: sequential network calls that produced the chunk (K scales, L tokens or N denoising steps).
        encoding_seconds: the part of `prediction_seconds` that turned the observations into the network's
            features (for an image policy the camera encoder; for a state policy only the normalization).
        repaired_chunks: how many of the B chunks came from tokens the tokenizer could not decode exactly and
            repaired (the next-token family over a kind such as FAST); None for a policy whose predictions always
            decode as they are.
    """

    actions: np.ndarray
    prediction_seconds: float
    decoding_seconds: float
    model_calls: int
    encoding_seconds: float = 0.0
    repaired_chunks: int | None = None


@dataclass(frozen=True)
class Deployment:
    """How evaluation workers obtain the policy they run, and the backend that will produce its latencies.

    Attributes:
        backend: name of the runtime that executes the policy (`torch`, `onnxruntime`); reported per row.
        load: picklable zero-argument callable that builds the policy inside a worker process; None to run the
            checkpoint itself in PyTorch, read by the caller (`carp.policies.registry.load_policy`), which the
            families cannot call without importing the registry that imports them.
    """

    backend: str
    load: Callable[[], Policy] | None


@runtime_checkable
class Policy(Protocol):
    """The seam between a policy family and carp's training, evaluation and reporting.

    Observations are raw (un-normalized) (B, To, Do) float arrays; actions come back raw (B, H, A) float32. Choosing
    the executed slice and converting rotations stay with the caller (`carp.evaluation.sources`).
    """

    policy_type: str
    metadata: dict[str, Any]
    tasks: Any
    """A multi-task policy's `carp.policies.tasks.PolicyTasks`; None for a single-task policy."""

    def select_task(self, task: str) -> None:
        """Evaluate `task` from now on; ValueError if the policy was not trained on it (`carp.policies.tasks`)."""
        ...

    def predict_action_timed(
        self,
        obs: np.ndarray | torch.Tensor,
        task_index: int | np.ndarray | torch.Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> TimedPrediction:
        """Predict one raw action chunk per observation and time it (inference mode).

        Args:
            obs: (B, To, Do) raw observations.
            task_index: None for single-task policies (and a multi-task policy's selected task); one index or (B,)
                otherwise.
            generator: random source of any sampling (top-k draws, diffusion noise), seeded per episode.
        """
        ...

    def predict_action(
        self,
        obs: np.ndarray | torch.Tensor,
        task_index: int | np.ndarray | torch.Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> np.ndarray:
        """(B, H, A) float32 raw actions; see :meth:`predict_action_timed`."""
        ...

    def configure_inference(self, **settings: Any) -> None:
        """Apply the family's inference settings (e.g. CARP's `top_k`); unknown names raise TypeError."""
        ...

    @property
    def model_calls_per_chunk(self) -> int:
        """Sequential network calls per chunk at the current inference settings."""
        ...

    @property
    def num_parameters(self) -> int:
        """Trained parameters (frozen parts such as a tokenizer excluded)."""
        ...

    @property
    def description(self) -> str:
        """Short human-readable name of the configuration for reports, e.g. `DDIM-10` or `greedy`."""
        ...

    @property
    def draws_random(self) -> bool:
        """Whether predictions at the current inference settings draw from the generator (sampling, noise).

        A policy that draws nothing predicts each row of a batch as it would alone, so a server may batch requests
        of several episodes; one that draws would give a batched row other draws than its episode's generator.
        """
        ...

    def training_loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Scalar float32 loss of one batch of normalized windows.

        Args:
            batch: `obs` (b, To, Do) and `actions` (b, H, A) normalized, `task_ids` (b,) long when multi-task.
        """
        ...

    def to_checkpoint(self) -> dict[str, Any]:
        """Self-contained state with `format_version` and `policy_type` (see the module docstring)."""
        ...

    def save(self, path: Path) -> None:
        """Atomically write :meth:`to_checkpoint` to `path`."""
        ...

    def to(self, device: str | torch.device) -> Policy:
        """Move the weights to `device`; returns the policy."""
        ...

    def train(self, mode: bool = True) -> Policy:
        """Training mode for the trained parts (frozen parts stay in eval mode); returns the policy."""
        ...

    def parameters(self) -> Iterator[torch.nn.Parameter]:
        """Parameters (frozen ones included; the optimizer takes those that require gradients)."""
        ...

    def deployment(self, checkpoint_path: Path, backend: str, directory: Path) -> Deployment:
        """How workers should run this policy when evaluation asks for `backend`.

        Args:
            checkpoint_path: where this policy's checkpoint lies (workers load it again).
            backend: the requested backend; a family that only runs in PyTorch answers with `torch`.
            directory: scratch space for exported graphs; removed after the evaluation.
        """
        ...


def count_parameters(module: torch.nn.Module) -> int:
    """Parameters of `module` that require gradients."""
    return sum(parameter.numel() for parameter in module.parameters() if parameter.requires_grad)


def check_dimensions(**dimensions: int) -> None:
    """Raise ValueError naming the first of the keyword `dimensions` (e.g. `obs_dim=...`) that is below 1."""
    for name, value in dimensions.items():
        if value < 1:
            raise ValueError(f"{name} must be >= 1, got {value}")


def check_observation_shape(observations: Any, obs_steps: int, obs_dim: int, name: str) -> None:
    """Raise ValueError unless `observations` is a (B, To, Do) tensor with these `To` and `Do`.

    Args:
        observations: the tensor to check.
        obs_steps: `To`.
        obs_dim: `Do`.
        name: the argument's name in the message.
    """
    if observations.dim() != 3 or tuple(observations.shape[1:]) != (obs_steps, obs_dim):
        raise ValueError(
            f"{name} must have shape (B, To, Do) = (B, {obs_steps}, {obs_dim}), got {tuple(observations.shape)}"
        )
