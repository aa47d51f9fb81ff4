"""The interface every action tokenizer kind implements, and the folder format every kind saves to.

A kind turns normalized action chunks (B, H, A) in [-1, 1] (per-task min-max statistics, `carp.data.normalizer`)
into integer tokens and back. Fixed-length kinds give every chunk L tokens; a variable-length kind (FAST) gives each
chunk its own count. Both travel in one :class:`TokenBatch`: ids (B, L_max) with the positions past a row's length
filled with :data:`PADDING_ID`, and the lengths (B,). Decoding never raises on a malformed sequence (a policy can
sample one): it returns a chunk for every row and flags the rows it had to repair (:class:`DecodedChunks`).

A saved tokenizer is a folder holding ``kind.json`` (the kind, :data:`KIND_FORMAT_VERSION` and the kind's settings
and fitted values) and whatever files the kind adds; `carp.tokenizer.kinds.registry.load_tokenizer` reads the kind
there and hands the folder to that kind's ``load``.
"""

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from carp.outputs import write_text

KIND_FORMAT_VERSION = 1
KIND_FILENAME = "kind.json"
PADDING_ID = -1
"""Fills a :class:`TokenBatch` row past its length; never a real token id (those are in [0, V))."""


@dataclass(frozen=True)
class TokenBatch:
    """Tokens of B chunks.

    Attributes:
        ids: (B, L_max) long token ids in [0, V), :data:`PADDING_ID` past each row's length; L_max = L for a
            fixed-length kind.
        lengths: (B,) long, the number of real tokens of each row.
    """

    ids: torch.Tensor
    lengths: torch.Tensor

    @classmethod
    def fixed(cls, ids: torch.Tensor) -> "TokenBatch":
        """A batch of a fixed-length kind from its (B, L) ids, every row L long."""
        return cls(ids, torch.full((ids.shape[0],), ids.shape[1], dtype=torch.long))

    @classmethod
    def from_sequences(cls, sequences: list[list[int]]) -> "TokenBatch":
        """A batch of variable-length rows, padded to the longest."""
        lengths = torch.tensor([len(sequence) for sequence in sequences], dtype=torch.long)
        ids = torch.full((len(sequences), int(lengths.max()) if sequences else 0), PADDING_ID, dtype=torch.long)
        for row, sequence in enumerate(sequences):
            ids[row, : len(sequence)] = torch.as_tensor(sequence, dtype=torch.long)
        return cls(ids, lengths)

    def sequences(self) -> list[list[int]]:
        """Each row's real tokens, padding dropped."""
        return [row[:length].tolist() for row, length in zip(self.ids, self.lengths.tolist(), strict=True)]


@dataclass(frozen=True)
class DecodedChunks:
    """Chunks decoded from tokens.

    Attributes:
        actions: (B, H, A) float32 normalized actions.
        invalid: (B,) bool, rows whose tokens did not form a well-formed chunk (a wrong count of values, or an id
            outside the vocabulary) and were repaired to decode at all (see each kind's ``decode``).
    """

    actions: torch.Tensor
    invalid: torch.Tensor

    @property
    def invalid_count(self) -> int:
        """How many rows were repaired."""
        return int(self.invalid.sum())


@dataclass(frozen=True)
class TokensPerChunk:
    """How many tokens a chunk takes: equal fields for a fixed-length kind, measured on the fitting windows else.

    Attributes:
        mean: mean tokens per chunk.
        p95: 95th percentile of tokens per chunk.
        maximum: the most tokens a chunk took.
    """

    mean: float
    p95: float
    maximum: int

    @classmethod
    def fixed(cls, length: int) -> "TokensPerChunk":
        """Every chunk ``length`` tokens long."""
        return cls(float(length), float(length), length)

    @classmethod
    def measured(cls, lengths: np.ndarray) -> "TokensPerChunk":
        """Statistics of observed token counts (N,)."""
        return cls(float(np.mean(lengths)), float(np.percentile(lengths, 95)), int(np.max(lengths)))


@runtime_checkable
class ActionTokenizer(Protocol):
    """An action tokenizer kind: normalized chunks (B, H, A) to tokens and back, deterministic for fixed inputs."""

    kind: str
    action_dim: int
    action_horizon: int

    @property
    def vocabulary_size(self) -> int:
        """V: token ids are in [0, V)."""
        ...

    @property
    def tokens_per_chunk(self) -> TokensPerChunk:
        """L, or its statistics for a variable-length kind."""
        ...

    def fit(self, windows: torch.Tensor) -> None:
        """Fit ranges, codebooks or weights on training windows (N, H, A) of normalized actions."""
        ...

    def encode(self, chunks: torch.Tensor) -> TokenBatch:
        """Tokens of normalized chunks (B, H, A) float."""
        ...

    def decode(self, tokens: TokenBatch) -> DecodedChunks:
        """Normalized chunks (B, H, A) of tokens, with the rows that had to be repaired flagged."""
        ...

    def save(self, directory: Path) -> None:
        """Write the tokenizer into ``directory`` (created if missing), ``kind.json`` included."""
        ...


def is_variable_length(tokenizer: ActionTokenizer) -> bool:
    """Whether the kind gives each chunk its own token count (FAST) rather than L tokens for every chunk.

    A kind declares it with a class attribute ``variable_length = True``; the fixed-length kinds need not declare it.
    """
    return bool(getattr(tokenizer, "variable_length", False))


def check_chunks(chunks: torch.Tensor, action_horizon: int, action_dim: int) -> None:
    """Refuse chunks that are not (B, H, A)."""
    if chunks.dim() != 3 or tuple(chunks.shape[1:]) != (action_horizon, action_dim):
        raise ValueError(
            f"chunks must have shape (B, H, A) = (B, {action_horizon}, {action_dim}), got {tuple(chunks.shape)}"
        )


def write_kind_file(directory: Path, kind: str, settings: dict[str, Any]) -> None:
    """Write ``kind.json``: the kind, the format version and the kind's settings and fitted values (JSON values)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    payload = {"kind": kind, "format_version": KIND_FORMAT_VERSION, "settings": settings}
    write_text(directory / KIND_FILENAME, json.dumps(payload, indent=2, sort_keys=True))


def read_kind_file(directory: Path) -> tuple[str, dict[str, Any]]:
    """(kind, settings) of a saved tokenizer folder.

    Raises:
        FileNotFoundError: no ``kind.json`` in ``directory``.
        ValueError: another format version, or no kind recorded; the message names the file.
    """
    path = Path(directory) / KIND_FILENAME
    if not path.exists():
        raise FileNotFoundError(f"{path}: no tokenizer kind file")
    payload = json.loads(path.read_text())
    version = payload.get("format_version")
    if version != KIND_FORMAT_VERSION:
        raise ValueError(f"{path}: format_version {version!r}, this code reads version {KIND_FORMAT_VERSION}")
    if not isinstance(payload.get("kind"), str):
        raise ValueError(f"{path}: records no tokenizer kind")
    return payload["kind"], dict(payload.get("settings", {}))


def expect_kind(directory: Path, kind: str) -> dict[str, Any]:
    """The settings in ``directory``'s ``kind.json``, refusing a folder of another kind (naming both)."""
    recorded, settings = read_kind_file(directory)
    if recorded != kind:
        raise ValueError(f"{Path(directory) / KIND_FILENAME}: a {recorded!r} tokenizer, not {kind!r}")
    return settings
