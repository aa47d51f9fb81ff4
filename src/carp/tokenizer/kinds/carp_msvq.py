"""CARP's per-dimension multi-scale residual VQ-VAE (`carp.tokenizer.tokenizer`) behind the kind interface.

The wrapper adds nothing to the module's arithmetic: ``encode`` is `MultiScaleActionTokenizer.encode_to_sequence`
and ``decode`` is ``decode_ids(sequence_to_ids(...))``, so tokens and chunks are those of the module itself (token
layout: docs/architecture.md, "Token layout and attention mask"; L = A * (s_1 + ... + s_K), V = ``codebook_size``,
each dimension's tokens indexing its own codebook). Its training is the ``train_tokenizer`` stage's
(`carp.training.tokenizer_trainer`, a layer above this one), so ``fit`` refuses; wrap a trained module instead, or
load the stage's artifact folder (``models/tokenizer/``) with :meth:`CarpMsvqTokenizer.from_artifact`.
"""

from pathlib import Path

import torch

from carp.tokenizer.artifact import load_tokenizer_artifact
from carp.tokenizer.kinds.base import (
    DecodedChunks,
    TokenBatch,
    TokensPerChunk,
    check_chunks,
    expect_kind,
    write_kind_file,
)
from carp.tokenizer.kinds.bins import repaired_ids
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer
from carp.training.checkpoint import atomic_torch_save, read_checkpoint

KIND = "carp_msvq"
WEIGHTS_FILENAME = "weights.pt"


class CarpMsvqTokenizer:
    """A trained `MultiScaleActionTokenizer`, used in eval mode.

    Args:
        module: the trained tokenizer.
    """

    kind = KIND

    def __init__(self, module: MultiScaleActionTokenizer) -> None:
        self.module = module.eval()
        self.action_dim, self.action_horizon = module.spec.action_dim, module.spec.action_horizon

    @classmethod
    def from_artifact(cls, directory: Path) -> "CarpMsvqTokenizer":
        """The tokenizer of a ``train_tokenizer`` artifact folder (`carp.tokenizer.artifact`)."""
        return cls(load_tokenizer_artifact(directory).tokenizer)

    @property
    def vocabulary_size(self) -> int:
        """V = ``codebook_size``."""
        return self.module.spec.codebook_size

    @property
    def tokens_per_chunk(self) -> TokensPerChunk:
        """L = A * (s_1 + ... + s_K)."""
        return TokensPerChunk.fixed(self.module.spec.tokens_per_chunk)

    def fit(self, windows: torch.Tensor) -> None:
        """Refuse: the multi-scale VQ-VAE trains in `carp.training.tokenizer_trainer` (``train_tokenizer``)."""
        raise RuntimeError(
            "carp_msvq trains with carp.training.tokenizer_trainer.train_tokenizer; wrap the trained module"
        )

    def encode(self, chunks: torch.Tensor) -> TokenBatch:
        """The module's token sequences (B, L) of chunks (B, H, A)."""
        check_chunks(chunks, self.action_horizon, self.action_dim)
        with torch.inference_mode():
            return TokenBatch.fixed(self.module.encode_to_sequence(chunks))

    def decode(self, tokens: TokenBatch) -> DecodedChunks:
        """The module's decoding (B, H, A); ids outside [0, V) or rows of another length are repaired and flagged."""
        ids, invalid = repaired_ids(tokens, self.module.spec.tokens_per_chunk, self.vocabulary_size)
        with torch.inference_mode():
            actions = self.module.decode_ids(self.module.sequence_to_ids(ids))
        return DecodedChunks(actions, invalid)

    def save(self, directory: Path) -> None:
        """Write ``kind.json`` and ``weights.pt``, the module's `MultiScaleActionTokenizer.to_checkpoint`."""
        write_kind_file(directory, KIND, {"spec": self.module.spec.to_dict()})
        atomic_torch_save(self.module.to_checkpoint(), Path(directory) / WEIGHTS_FILENAME)

    @classmethod
    def load(cls, directory: Path) -> "CarpMsvqTokenizer":
        """Read a folder written by :meth:`save`."""
        expect_kind(directory, KIND)
        checkpoint = read_checkpoint(Path(directory) / WEIGHTS_FILENAME, weights_only=True)
        return cls(MultiScaleActionTokenizer.from_checkpoint(checkpoint))
