"""The tokenizer artifact: the directory ``models/tokenizer/`` that training writes and the registry ships.

Contents: ``tokenizer.pt`` (spec, weights, the action statistics of every task it was trained on, action space) and
``tokenizer.json`` (the same metadata readable without torch, plus the weights' sha256). The sha256 is computed over
the tensors themselves (sorted names, shapes, float32 bytes) and the statistics, not over the pickle, so equal
weights give equal hashes whatever torch.save does; it makes registration idempotent and lets a policy refuse a
tokenizer that is not the one it names.

Normalization is per task: the tokenizer sees each task's actions scaled to [-1, 1] by that task's own min-max
statistics, and a policy always uses the statistics of its own task (also for a task the tokenizer never saw). With
one statistics for the union of tasks, a task whose actions span a small part of the union's range would be encoded
with a fraction of the codebook's resolution: Square's y span is 37% of the Lift + Can + Square union, and a shared
tokenizer trained that way replayed 65 of 100 Square demos open loop (`carp.evaluation.replay`) against 90 with
per-task statistics and 83 for Square's own tokenizer.
"""

import hashlib
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from carp.data.normalizer import MinMaxNormalizer
from carp.outputs import atomic_path, write_text
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer
from carp.training.checkpoint import CheckpointError, one_line, read_checkpoint

WEIGHTS_FILENAME = "tokenizer.pt"
METADATA_FILENAME = "tokenizer.json"


class TokenizerMismatchError(ValueError):
    """A tokenizer that does not fit the policy's params, or whose weights are not the ones referenced."""


class NonFiniteTokenizerError(ValueError):
    """A tokenizer whose training loss, weights, action statistics or held-out metrics are not all finite."""


@dataclass
class TokenizerArtifact:
    """A loaded tokenizer with what is needed to use it on raw actions."""

    tokenizer: MultiScaleActionTokenizer
    action_normalizers: dict[str, MinMaxNormalizer]  # task -> the statistics its windows were normalized with
    action_space: str
    sha256: str
    metrics: dict[str, float] = field(default_factory=dict)  # held-out metrics measured when it was saved

    @classmethod
    def build(
        cls,
        tokenizer: MultiScaleActionTokenizer,
        action_normalizers: Mapping[str, MinMaxNormalizer],
        action_space: str,
        metrics: Mapping[str, float] | None = None,
    ) -> "TokenizerArtifact":
        """An artifact of a trained tokenizer, its training tasks' statistics, action space and held-out metrics.

        The sha256 covers the weights and statistics, not the metrics.
        """
        if not action_normalizers:
            raise ValueError("a tokenizer artifact needs the action statistics of at least one training task")
        normalizers = dict(action_normalizers)
        measured = {key: float(value) for key, value in (metrics or {}).items()}
        return cls(tokenizer, normalizers, action_space, weights_sha256(tokenizer, normalizers), measured)

    def to_payload(self) -> dict[str, Any]:
        """What ``tokenizer.pt`` holds, and a policy checkpoint embeds: spec, weights, statistics, space, metrics."""
        return {
            **self.tokenizer.to_checkpoint(),
            "action_normalizers": {task: normalizer.to_dict() for task, normalizer in self.action_normalizers.items()},
            "action_space": self.action_space,
            "metrics": dict(self.metrics),
        }

    @classmethod
    def from_payload(
        cls,
        payload: dict[str, Any],
        expected_sha256: str | None = None,
        recorded_in: str = "the reference",
        map_location: str | torch.device = "cpu",
    ) -> "TokenizerArtifact":
        """Rebuild an artifact from :meth:`to_payload` output, loading the weights strictly.

        Args:
            payload: the stored dict.
            expected_sha256: when given, the weights and statistics must hash to it.
            recorded_in: where ``expected_sha256`` comes from, for the error message (e.g. a reference file).
            map_location: device of the weights.

        Raises:
            TokenizerMismatchError: the hash differs from ``expected_sha256`` (both hashes named), or the payload
                predates per-task normalization (one set of statistics for all tasks).
            KeyError, RuntimeError, ValueError: the payload is incomplete or its weights do not fit its spec.
        """
        if not isinstance(payload, dict):
            raise ValueError(f"not a tokenizer: the file holds a {type(payload).__name__}, not a dict")
        if "action_normalizers" not in payload:
            raise TokenizerMismatchError(
                "tokenizer saved with one action normalization for all its tasks (carp before per-task "
                "normalization); train it again"
            )
        tokenizer = MultiScaleActionTokenizer.from_checkpoint(payload).to(map_location).eval()
        normalizers = {task: MinMaxNormalizer.from_dict(state) for task, state in payload["action_normalizers"].items()}
        artifact = cls.build(tokenizer, normalizers, payload["action_space"], payload.get("metrics"))
        if expected_sha256 is not None and artifact.sha256 != expected_sha256:
            raise TokenizerMismatchError(
                f"tokenizer weights have sha256 {artifact.sha256[:12]}..., not the sha256 {expected_sha256[:12]}... "
                f"recorded in {recorded_in}"
            )
        return artifact

    @property
    def tasks(self) -> list[str]:
        """The tasks whose demos trained the tokenizer."""
        return list(self.action_normalizers)

    def action_normalizer(self, task: str | None = None) -> MinMaxNormalizer:
        """The statistics of one training task; ``task`` may be omitted when there is only one.

        Raises:
            KeyError: ``task`` is not a training task, or omitted with several; the message names the choices.
        """
        return task_normalizer(self.action_normalizers, task)


def task_normalizer(normalizers: Mapping[str, MinMaxNormalizer], task: str | None) -> MinMaxNormalizer:
    """The action statistics of `task` among a tokenizer's training tasks; None picks the only one.

    Raises:
        KeyError: ``task`` is not a training task, or None with several; the message names the choices.
    """
    if task is None and len(normalizers) == 1:
        return next(iter(normalizers.values()))
    if task is None:
        raise KeyError(
            f"the tokenizer was trained on {list(normalizers)}: name the task whose action statistics to use"
        )
    if task not in normalizers:
        raise KeyError(f"task {task!r} is not one of the tokenizer's training tasks {list(normalizers)}")
    return normalizers[task]


def weights_sha256(tokenizer: MultiScaleActionTokenizer, action_normalizers: Mapping[str, MinMaxNormalizer]) -> str:
    """Content hash of the tokenizer's weights and of each training task's normalization (in task order)."""
    digest = hashlib.sha256()
    for name, tensor in sorted(tokenizer.state_dict().items()):
        values = tensor.detach().to("cpu").contiguous()
        digest.update(name.encode())
        digest.update(str(tuple(values.shape)).encode())
        digest.update(
            values.to(torch.float32).numpy().tobytes() if values.is_floating_point() else values.numpy().tobytes()
        )
    for task, normalizer in action_normalizers.items():
        digest.update(task.encode())
        for array in (normalizer.minimum, normalizer.maximum):
            digest.update(np.asarray(array, dtype=np.float64).tobytes())
    return digest.hexdigest()


def require_finite(
    tokenizer: MultiScaleActionTokenizer,
    action_normalizers: Mapping[str, MinMaxNormalizer],
    metrics: Mapping[str, float],
    where: str,
) -> None:
    """Refuse a tokenizer with a NaN or infinite weight, action statistic (in float32) or metric.

    Raises:
        NonFiniteTokenizerError: one line naming ``where`` and the first weight, statistic or metric that is not
            finite.
    """
    for name, tensor in tokenizer.state_dict().items():
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise NonFiniteTokenizerError(f"{where}: weight {name}: holds NaN or inf (training diverged)")
    for task, normalizer in action_normalizers.items():
        # Float32 is the dtype the statistics are applied in (replay buffer, ONNX graphs).
        for label, values in (("minimum", normalizer.minimum), ("maximum", normalizer.maximum)):
            with np.errstate(over="ignore"):
                finite = np.isfinite(np.asarray(values, dtype=np.float64).astype(np.float32))
            if not finite.all():
                raise NonFiniteTokenizerError(
                    f"{where}: action statistics of {task}: {label}={np.asarray(values).tolist()}: not finite"
                )
    for key, value in metrics.items():
        if not math.isfinite(value):
            raise NonFiniteTokenizerError(
                f"{where}: metric {key}={value!r}: not finite (training diverged, or the data's range is too wide)"
            )


def save_tokenizer_artifact(
    directory: Path,
    tokenizer: MultiScaleActionTokenizer,
    action_normalizers: Mapping[str, MinMaxNormalizer],
    action_space: str,
    metrics: Mapping[str, float] | None = None,
) -> str:
    """Write the artifact into ``directory`` (files replaced atomically); returns the weights' sha256.

    Args:
        directory: created if missing; ``tokenizer.pt`` and ``tokenizer.json`` are written into it.
        tokenizer: the trained tokenizer.
        action_normalizers: training task -> the statistics its windows were normalized with, in training order.
        action_space: e.g. ``panda-abs10``; a policy refuses a tokenizer of another action space.
        metrics: held-out metrics, stored with the tokenizer so that the registry can check them.

    Raises:
        NonFiniteTokenizerError: a weight, statistic or metric is not finite; nothing is written.
    """
    artifact = TokenizerArtifact.build(tokenizer, action_normalizers, action_space, metrics)
    require_finite(tokenizer, artifact.action_normalizers, artifact.metrics, str(directory))
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    payload = artifact.to_payload()
    metadata = {
        "spec": tokenizer.spec.to_dict(),
        "action_space": action_space,
        "tasks": artifact.tasks,
        "sha256": artifact.sha256,
        "metrics": artifact.metrics,
    }
    with atomic_path(directory / WEIGHTS_FILENAME) as temporary, open(temporary, "wb") as handle:
        torch.save(payload, handle)
    write_text(directory / METADATA_FILENAME, json.dumps(metadata, indent=2))
    return artifact.sha256


def load_tokenizer_artifact(
    directory: Path,
    expected_sha256: str | None = None,
    map_location: str | torch.device = "cpu",
    recorded_in: str = "the reference",
) -> TokenizerArtifact:
    """Load an artifact directory; with ``expected_sha256``, refuse weights that hash differently.

    Every error message is one line that starts with the weights file's path.

    Args:
        directory: the artifact directory.
        expected_sha256: the hash the weights must have, or None.
        map_location: device of the weights.
        recorded_in: where ``expected_sha256`` comes from (e.g. ``models/tokenizer_ref.json``), for the message.

    Raises:
        FileNotFoundError: no artifact in ``directory``.
        CheckpointError: the weights file is truncated or corrupt, incomplete, or its weights do not fit its spec.
        TokenizerMismatchError: the weights' hash differs from ``expected_sha256``, or the artifact predates
            per-task normalization (one set of statistics for all tasks).
        NonFiniteTokenizerError: a weight, statistic or stored metric is not finite.
    """
    path = Path(directory) / WEIGHTS_FILENAME
    if not path.exists():
        raise FileNotFoundError(f"{path}: tokenizer weights not found")
    payload = read_checkpoint(path, weights_only=True)
    try:
        artifact = TokenizerArtifact.from_payload(payload, expected_sha256, recorded_in, map_location)
    except TokenizerMismatchError as error:
        raise TokenizerMismatchError(f"{path}: {error}") from error
    except KeyError as error:
        raise CheckpointError(f"{path}: tokenizer file lacks the entry {error}") from error
    except (AttributeError, RuntimeError, TypeError, ValueError) as error:
        raise CheckpointError(f"{path}: {one_line(error)}") from error
    require_finite(artifact.tokenizer, artifact.action_normalizers, artifact.metrics, str(path))
    return artifact


def check_compatible(
    artifact: TokenizerArtifact, action_space: str, scales: tuple[int, ...], codebook_size: int
) -> None:
    """Refuse a tokenizer whose action space, scales or codebook size differ from the policy's params.

    Raises:
        TokenizerMismatchError: names the first field that differs and both values.
    """
    spec = artifact.tokenizer.spec
    for field_name, theirs, ours in (
        ("action space", artifact.action_space, action_space),
        ("scales", tuple(spec.scales), tuple(scales)),
        ("codebook_size", spec.codebook_size, codebook_size),
    ):
        if theirs != ours:
            raise TokenizerMismatchError(
                f"tokenizer {field_name} is {list(theirs) if isinstance(theirs, tuple) else theirs!r} but the params "
                f"ask for {list(ours) if isinstance(ours, tuple) else ours!r}"
            )
