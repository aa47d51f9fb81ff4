"""The tokenizer artifact: the directory ``models/tokenizer/`` that training writes and the registry ships.

Contents: ``tokenizer.pt`` (spec, weights, the action normalization it was trained with, action space, tasks) and
``tokenizer.json`` (the same metadata readable without torch, plus the weights' sha256). The sha256 is computed over
the tensors themselves (sorted names, shapes, float32 bytes) and the normalization, not over the pickle, so equal
weights give equal hashes whatever torch.save does; it makes registration idempotent and lets a policy refuse a
tokenizer that is not the one it names.
"""

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from carp.data.normalizer import MinMaxNormalizer
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer

WEIGHTS_FILENAME = "tokenizer.pt"
METADATA_FILENAME = "tokenizer.json"


class TokenizerMismatchError(ValueError):
    """A tokenizer that does not fit the policy's params, or whose weights are not the ones referenced."""


@dataclass
class TokenizerArtifact:
    """A loaded tokenizer with what is needed to use it on raw actions."""

    tokenizer: MultiScaleActionTokenizer
    action_normalizer: MinMaxNormalizer
    action_space: str
    tasks: list[str]
    sha256: str


def weights_sha256(tokenizer: MultiScaleActionTokenizer, action_normalizer: MinMaxNormalizer) -> str:
    """Content hash of the tokenizer's weights and normalization."""
    digest = hashlib.sha256()
    for name, tensor in sorted(tokenizer.state_dict().items()):
        values = tensor.detach().to("cpu").contiguous()
        digest.update(name.encode())
        digest.update(str(tuple(values.shape)).encode())
        digest.update(
            values.to(torch.float32).numpy().tobytes() if values.is_floating_point() else values.numpy().tobytes()
        )
    for array in (action_normalizer.minimum, action_normalizer.maximum):
        digest.update(np.asarray(array, dtype=np.float64).tobytes())
    return digest.hexdigest()


def save_tokenizer_artifact(
    directory: Path,
    tokenizer: MultiScaleActionTokenizer,
    action_normalizer: MinMaxNormalizer,
    action_space: str,
    tasks: list[str],
) -> str:
    """Write the artifact into ``directory`` (files replaced atomically); returns the weights' sha256."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    sha256 = weights_sha256(tokenizer, action_normalizer)
    payload = {
        **tokenizer.to_checkpoint(),
        "action_normalizer": action_normalizer.to_dict(),
        "action_space": action_space,
        "tasks": list(tasks),
    }
    metadata = {
        "spec": tokenizer.spec.to_dict(),
        "action_space": action_space,
        "tasks": list(tasks),
        "sha256": sha256,
    }
    for filename, write in (
        (WEIGHTS_FILENAME, lambda path: torch.save(payload, path)),
        (METADATA_FILENAME, lambda path: path.write_text(json.dumps(metadata, indent=2))),
    ):
        temporary = directory / f".{filename}.tmp"
        write(temporary)
        os.replace(temporary, directory / filename)
    return sha256


def load_tokenizer_artifact(
    directory: Path, expected_sha256: str | None = None, map_location: str | torch.device = "cpu"
) -> TokenizerArtifact:
    """Load an artifact directory; with ``expected_sha256``, refuse weights that hash differently.

    Raises:
        FileNotFoundError: no artifact in ``directory``.
        TokenizerMismatchError: the weights' hash differs from ``expected_sha256``.
    """
    path = Path(directory) / WEIGHTS_FILENAME
    if not path.exists():
        raise FileNotFoundError(f"{path}: tokenizer weights not found")
    payload = torch.load(path, map_location=map_location, weights_only=False)
    tokenizer = MultiScaleActionTokenizer.from_checkpoint(payload).to(map_location).eval()
    normalizer = MinMaxNormalizer.from_dict(payload["action_normalizer"])
    sha256 = weights_sha256(tokenizer, normalizer)
    if expected_sha256 is not None and sha256 != expected_sha256:
        raise TokenizerMismatchError(
            f"{path}: weights sha256 {sha256[:12]}... differs from the referenced {expected_sha256[:12]}..."
        )
    return TokenizerArtifact(tokenizer, normalizer, payload["action_space"], list(payload["tasks"]), sha256)


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
