"""The artifact of a tokenizer kind other than ``carp_msvq``: the kind's saved folder plus what the pipeline adds.

``carp_msvq`` keeps its own artifact (`carp.tokenizer.artifact`: ``tokenizer.pt`` and ``tokenizer.json``). Every other
kind's ``train_tokenizer`` output is the folder the kind saves (``kind.json`` and its own files,
`carp.tokenizer.kinds.base`) plus ``tokenizer.json``: the kind, the action space, each training task's action
statistics (normalization is per task, as for ``carp_msvq``), the held-out metrics and a sha256. The sha256 covers
the kind's files (names and bytes, in name order) and the statistics, so the registry can register a folder once
and check a download; the metrics are not part of it.
"""

import hashlib
import json
import math
import shutil
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from carp.config.tokenizer_kinds import DEFAULT_TOKENIZER_KIND
from carp.data.normalizer import MinMaxNormalizer
from carp.outputs import write_text
from carp.tokenizer.artifact import (
    METADATA_FILENAME,
    NonFiniteTokenizerError,
    TokenizerArtifact,
    TokenizerMismatchError,
    check_compatible,
    load_tokenizer_artifact,
    task_normalizer,
)
from carp.tokenizer.kinds.base import KIND_FILENAME, ActionTokenizer
from carp.tokenizer.kinds.registry import load_tokenizer


@dataclass
class KindArtifact:
    """A loaded tokenizer of any kind with its training tasks' statistics, action space, sha256 and metrics."""

    tokenizer: ActionTokenizer
    action_normalizers: dict[str, MinMaxNormalizer]
    action_space: str
    sha256: str
    metrics: dict[str, float] = field(default_factory=dict)
    directory: Path | None = None  # the folder it was loaded from, whose files a copy keeps byte for byte
    files: dict[str, bytes] | None = None  # the kind's files when it came from a payload (a policy checkpoint)

    @property
    def kind(self) -> str:
        """The tokenizer's kind."""
        return self.tokenizer.kind

    @property
    def tasks(self) -> list[str]:
        """The tasks whose demos fitted the tokenizer."""
        return list(self.action_normalizers)

    def action_normalizer(self, task: str | None = None) -> MinMaxNormalizer:
        """The statistics of one training task; ``task`` may be omitted when there is only one.

        Raises:
            KeyError: ``task`` is not a training task, or omitted with several; the message names the choices.
        """
        return task_normalizer(self.action_normalizers, task)

    def kind_files(self) -> dict[str, bytes]:
        """The kind's files, relative POSIX name -> bytes (``tokenizer.json`` left out): what the sha256 covers.

        Taken byte for byte from the payload or folder the artifact came from, so that the sha256 holds for a copy;
        saved afresh only for a tokenizer that has neither.
        """
        if self.files is not None:
            return dict(self.files)
        if self.directory is not None:
            return _read_kind_files(self.directory)
        with tempfile.TemporaryDirectory(prefix="carp-kind-") as scratch:
            self.tokenizer.save(Path(scratch))
            return _read_kind_files(Path(scratch))

    def to_payload(self) -> dict[str, Any]:
        """What a policy checkpoint embeds to decode without the pipeline's folder: the kind's files and statistics."""
        return {
            "kind": self.kind,
            "files": self.kind_files(),
            "action_normalizers": {task: normalizer.to_dict() for task, normalizer in self.action_normalizers.items()},
            "action_space": self.action_space,
            "metrics": dict(self.metrics),
        }

    @classmethod
    def from_payload(
        cls, payload: dict[str, Any], expected_sha256: str | None = None, recorded_in: str = "the reference"
    ) -> "KindArtifact":
        """Rebuild an artifact from :meth:`to_payload` output: its files are loaded through a temporary folder.

        Raises:
            TokenizerMismatchError: the files and statistics hash differently from ``expected_sha256`` (both named).
            ValueError: a file name that leaves the folder, or files of another kind than the payload names.
            KeyError: the payload is incomplete.
        """
        files = dict(payload["files"])
        normalizers = {task: MinMaxNormalizer.from_dict(state) for task, state in payload["action_normalizers"].items()}
        with tempfile.TemporaryDirectory(prefix="carp-kind-") as scratch:
            folder = Path(scratch)
            for name, content in files.items():
                target = folder / name
                if Path(name).is_absolute() or ".." in Path(name).parts:
                    raise ValueError(f"tokenizer file name {name!r} leaves the tokenizer's folder")
                target.parent.mkdir(parents=True, exist_ok=True)
                target.write_bytes(content)
            tokenizer = load_tokenizer(folder)
            sha256 = folder_sha256(folder, normalizers)
        if tokenizer.kind != payload["kind"]:
            raise ValueError(f"the embedded tokenizer files are of kind {tokenizer.kind!r}, not {payload['kind']!r}")
        if expected_sha256 is not None and sha256 != expected_sha256:
            raise TokenizerMismatchError(
                f"tokenizer files have sha256 {sha256[:12]}..., not the sha256 {expected_sha256[:12]}... "
                f"recorded in {recorded_in}"
            )
        metrics = {key: float(value) for key, value in payload.get("metrics", {}).items()}
        return cls(tokenizer, normalizers, payload["action_space"], sha256, metrics, None, files)


def _read_kind_files(directory: Path) -> dict[str, bytes]:
    directory = Path(directory)
    return {
        path.relative_to(directory).as_posix(): path.read_bytes()
        for path in sorted(p for p in directory.rglob("*") if p.is_file() and p.name != METADATA_FILENAME)
    }


def is_kind_artifact(directory: Path) -> bool:
    """Whether ``directory`` holds a kind's folder (``kind.json``) rather than ``carp_msvq``'s artifact."""
    return (Path(directory) / KIND_FILENAME).exists()


def folder_sha256(directory: Path, action_normalizers: Mapping[str, MinMaxNormalizer]) -> str:
    """Content hash of the kind's files in ``directory`` (``tokenizer.json`` left out) and the statistics."""
    digest = hashlib.sha256()
    directory = Path(directory)
    for path in sorted(p for p in directory.rglob("*") if p.is_file() and p.name != METADATA_FILENAME):
        digest.update(path.relative_to(directory).as_posix().encode())
        digest.update(path.read_bytes())
    for task, normalizer in action_normalizers.items():
        digest.update(task.encode())
        for array in (normalizer.minimum, normalizer.maximum):
            digest.update(np.asarray(array, dtype=np.float64).tobytes())
    return digest.hexdigest()


def _require_finite(metrics: Mapping[str, float], normalizers: Mapping[str, MinMaxNormalizer], where: str) -> None:
    for task, normalizer in normalizers.items():
        for label, values in (("minimum", normalizer.minimum), ("maximum", normalizer.maximum)):
            if not np.isfinite(np.asarray(values, dtype=np.float64).astype(np.float32)).all():
                raise NonFiniteTokenizerError(
                    f"{where}: action statistics of {task}: {label}={np.asarray(values).tolist()}: not finite"
                )
    for key, value in metrics.items():
        if not math.isfinite(value):
            raise NonFiniteTokenizerError(f"{where}: metric {key}={value!r}: not finite")


def save_kind_artifact(
    directory: Path,
    tokenizer: ActionTokenizer,
    action_normalizers: Mapping[str, MinMaxNormalizer],
    action_space: str,
    metrics: Mapping[str, float] | None = None,
    files_from: Path | None = None,
) -> str:
    """Write the fitted ``tokenizer`` and ``tokenizer.json`` into ``directory``, emptied first; returns the sha256.

    With ``files_from`` (a loaded artifact's folder, e.g. a registered version's download) the kind's files are
    copied from there byte for byte instead of saved again, so the copy keeps the registered sha256.

    Raises:
        NonFiniteTokenizerError: a statistic or metric is not finite; nothing is written.
        ValueError: no training task's statistics.
    """
    if not action_normalizers:
        raise ValueError("a tokenizer artifact needs the action statistics of at least one training task")
    measured = {key: float(value) for key, value in (metrics or {}).items()}
    _require_finite(measured, action_normalizers, str(directory))
    directory = Path(directory)
    # The stage's folder may hold another kind's files from an earlier run outside DVC; they must not be hashed.
    if directory.exists():
        shutil.rmtree(directory)
    if files_from is None:
        tokenizer.save(directory)
    else:
        shutil.copytree(files_from, directory, ignore=shutil.ignore_patterns(METADATA_FILENAME))
    sha256 = folder_sha256(directory, action_normalizers)
    metadata = {
        "kind": tokenizer.kind,
        "action_space": action_space,
        "action_horizon": tokenizer.action_horizon,
        "action_dim": tokenizer.action_dim,
        "tasks": list(action_normalizers),
        "action_normalizers": {task: normalizer.to_dict() for task, normalizer in action_normalizers.items()},
        "sha256": sha256,
        "metrics": measured,
    }
    write_text(directory / METADATA_FILENAME, json.dumps(metadata, indent=2))
    return sha256


def load_kind_artifact(
    directory: Path, expected_sha256: str | None = None, recorded_in: str = "the reference"
) -> KindArtifact:
    """Load a folder written by :func:`save_kind_artifact`; with ``expected_sha256``, refuse other contents.

    Raises:
        FileNotFoundError: no ``tokenizer.json`` or ``kind.json`` in ``directory``.
        TokenizerMismatchError: the contents hash differently from ``expected_sha256`` (both named) or from the
            hash ``tokenizer.json`` records.
        NonFiniteTokenizerError: a statistic or stored metric is not finite.
    """
    directory = Path(directory)
    path = directory / METADATA_FILENAME
    if not path.exists():
        raise FileNotFoundError(f"{path}: tokenizer metadata not found")
    metadata = json.loads(path.read_text())
    normalizers = {task: MinMaxNormalizer.from_dict(state) for task, state in metadata["action_normalizers"].items()}
    sha256 = folder_sha256(directory, normalizers)
    for expected, where in ((metadata.get("sha256"), str(path)), (expected_sha256, str(recorded_in))):
        if expected and sha256 != expected:
            raise TokenizerMismatchError(
                f"{directory}: tokenizer files have sha256 {sha256[:12]}..., not the sha256 {expected[:12]}... "
                f"recorded in {where}"
            )
    metrics = {key: float(value) for key, value in metadata.get("metrics", {}).items()}
    _require_finite(metrics, normalizers, str(path))
    return KindArtifact(load_tokenizer(directory), normalizers, metadata["action_space"], sha256, metrics, directory)


def check_kind_compatible(artifact: KindArtifact, kind: str, action_space: str, action_horizon: int) -> None:
    """Refuse a tokenizer of another kind, action space or horizon than the params ask for.

    Raises:
        TokenizerMismatchError: names the first key that differs and both values.
    """
    for key, theirs, ours in (
        ("tokenizer.kind", artifact.kind, kind),
        ("action space", artifact.action_space, action_space),
        ("data.action_horizon", artifact.tokenizer.action_horizon, action_horizon),
    ):
        if theirs != ours:
            raise TokenizerMismatchError(f"{key} is {theirs!r} in the tokenizer but the params ask for {ours!r}")


def load_any_artifact(
    directory: Path, expected_sha256: str | None = None, recorded_in: str = "the reference"
) -> TokenizerArtifact | KindArtifact:
    """``carp_msvq``'s artifact (`carp.tokenizer.artifact`) or another kind's, whichever ``directory`` holds.

    Raises:
        as `carp.tokenizer.artifact.load_tokenizer_artifact` and :func:`load_kind_artifact`.
    """
    if is_kind_artifact(directory):
        return load_kind_artifact(directory, expected_sha256, recorded_in)
    return load_tokenizer_artifact(directory, expected_sha256, recorded_in=recorded_in)


def artifact_kind(artifact: TokenizerArtifact | KindArtifact) -> str:
    """The kind of either artifact."""
    return artifact.kind if isinstance(artifact, KindArtifact) else DEFAULT_TOKENIZER_KIND


def check_fits_params(
    artifact: TokenizerArtifact | KindArtifact,
    kind: str,
    action_space: str,
    action_horizon: int,
    scales: tuple[int, ...],
    codebook_size: int,
) -> None:
    """Refuse an artifact whose kind differs from ``kind``, then apply that kind's own checks.

    ``carp_msvq`` must match the action space, ``scales`` and ``codebook_size``
    (`carp.tokenizer.artifact.check_compatible`); another kind its action space and horizon.

    Raises:
        TokenizerMismatchError: names the first key that differs and both values.
    """
    theirs = artifact_kind(artifact)
    if theirs != kind:
        raise TokenizerMismatchError(f"tokenizer.kind is {theirs!r} in the tokenizer but the params ask for {kind!r}")
    if isinstance(artifact, KindArtifact):
        check_kind_compatible(artifact, kind, action_space, action_horizon)
    else:
        check_compatible(artifact, action_space, scales, codebook_size)
