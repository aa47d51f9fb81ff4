"""FAST (Pertsch et al. 2025, arXiv 2501.09747): DCT over time, scaled and rounded, then byte-pair encoded.

Each dimension of a normalized chunk is transformed with the orthonormal DCT-II along time (`scipy.fft.dct`), the
coefficients multiplied by ``scale`` and rounded to integers, and the H x A integers flattened frequency-major
(``[frequency 0: d0..d(A-1), frequency 1: ...]``, the low frequencies of every dimension first, so that the long
runs of zeros of high frequencies end the sequence). Each integer becomes one character of an alphabet covering the
integers seen on the training windows, and a byte-pair encoding with a vocabulary of V tokens, trained on those
windows with Hugging Face `tokenizers`, compresses the character string. The token count varies per chunk.

Decoding reverses it. A sequence a policy samples can decode to another count of integers than H x A, or hold an
id outside the vocabulary: such a row is repaired (unknown ids dropped, then the integers truncated or padded with
zero coefficients) and flagged invalid, so the caller can count it.

Deviations from FAST: the chunks arrive min-max normalized to [-1, 1] (carp's per-task statistics) instead of
1st-99th-quantile normalized, and an integer outside the range seen in training is clipped to it (the alphabet is
fixed when the encoding is trained).
"""

from pathlib import Path

import numpy as np
import torch
from einops import rearrange
from scipy.fft import dct, idct
from tokenizers import Tokenizer, models, trainers

from carp.outputs import write_text
from carp.tokenizer.kinds.base import (
    DecodedChunks,
    TokenBatch,
    TokensPerChunk,
    check_chunks,
    expect_kind,
    write_kind_file,
)

KIND = "fast"
ENCODING_FILENAME = "bpe.json"
# First code point of the integer alphabet: CJK ideographs, a block of ordinary letters that no normalization or
# whitespace rule of `tokenizers` touches.
ALPHABET_START = 0x4E00


class FastTokenizer:
    """DCT coefficients, scaled and rounded, compressed by a byte-pair encoding.

    Args:
        action_dim: A.
        action_horizon: H.
        scale: multiplies the orthonormal DCT coefficients before rounding (the rate knob: larger keeps more
            precision and makes longer sequences).
        vocabulary_size: V requested from the byte-pair encoding (at least the integer alphabet's size; the trained
            vocabulary can be smaller when merges run out).
    """

    kind = KIND
    variable_length = True

    def __init__(self, action_dim: int, action_horizon: int, scale: float = 10.0, vocabulary_size: int = 1024) -> None:
        self.action_dim, self.action_horizon = action_dim, action_horizon
        self.scale, self.requested_vocabulary_size = scale, vocabulary_size
        self.encoding: Tokenizer | None = None
        self.minimum = self.maximum = 0
        self.lengths = TokensPerChunk.fixed(0)

    @classmethod
    def from_config(cls, config, action_dim: int, action_horizon: int) -> "FastTokenizer":
        """Built from a `carp.config.tokenizer_kinds.FastConfig`."""
        return cls(action_dim, action_horizon, config.scale, config.vocabulary_size)

    @property
    def vocabulary_size(self) -> int:
        """V of the trained encoding."""
        return self._encoding().get_vocab_size()

    @property
    def tokens_per_chunk(self) -> TokensPerChunk:
        """Mean, 95th percentile and maximum token count on the fitting windows."""
        return self.lengths

    def coefficients(self, chunks: torch.Tensor) -> np.ndarray:
        """Rounded scaled DCT coefficients (B, H * A) int64 of chunks (B, H, A), frequency-major."""
        check_chunks(chunks, self.action_horizon, self.action_dim)
        transformed = dct(chunks.double().numpy(), type=2, norm="ortho", axis=1)  # (B, H, A)
        return rearrange(np.rint(transformed * self.scale).astype(np.int64), "b h a -> b (h a)")

    def chunks_of(self, coefficients: np.ndarray) -> torch.Tensor:
        """Chunks (B, H, A) float32 of integer coefficients (B, H * A), frequency-major."""
        transformed = rearrange(coefficients.astype(np.float64) / self.scale, "b (h a) -> b h a", a=self.action_dim)
        return torch.as_tensor(idct(transformed, type=2, norm="ortho", axis=1), dtype=torch.float32)

    def fit(self, windows: torch.Tensor) -> None:
        """Fix the integer alphabet and train the byte-pair encoding on training windows (N, H, A)."""
        coefficients = self.coefficients(windows)
        self.minimum, self.maximum = int(coefficients.min()), int(coefficients.max())
        alphabet = [chr(ALPHABET_START + value) for value in range(self.maximum - self.minimum + 1)]
        if len(alphabet) > self.requested_vocabulary_size:
            raise ValueError(
                f"vocabulary_size {self.requested_vocabulary_size} is below the {len(alphabet)} integers the "
                f"coefficients take at scale {self.scale}: raise it or lower the scale"
            )
        encoding = Tokenizer(models.BPE())
        trainer = trainers.BpeTrainer(
            vocab_size=self.requested_vocabulary_size,
            initial_alphabet=alphabet,
            limit_alphabet=len(alphabet),
            show_progress=False,
        )
        encoding.train_from_iterator(self._strings(coefficients), trainer=trainer)
        self.encoding = encoding
        self.lengths = TokensPerChunk.measured(self.encode(windows).lengths.numpy())

    def _encoding(self) -> Tokenizer:
        if self.encoding is None:
            raise RuntimeError("the FAST tokenizer has no byte-pair encoding yet: fit it on training windows first")
        return self.encoding

    def _strings(self, coefficients: np.ndarray) -> list[str]:
        clipped = np.clip(coefficients, self.minimum, self.maximum) - self.minimum + ALPHABET_START
        return ["".join(map(chr, row)) for row in clipped.tolist()]

    def encode(self, chunks: torch.Tensor) -> TokenBatch:
        """Variable-length token rows (B, L_max) with their lengths (B,) of chunks (B, H, A)."""
        encoded = self._encoding().encode_batch(self._strings(self.coefficients(chunks)))
        return TokenBatch.from_sequences([item.ids for item in encoded])

    def decode(self, tokens: TokenBatch) -> DecodedChunks:
        """Chunks (B, H, A); rows that do not decode to exactly H * A integers are repaired and flagged."""
        encoding = self._encoding()
        count = self.action_horizon * self.action_dim
        coefficients = np.zeros((tokens.ids.shape[0], count), dtype=np.int64)
        invalid = torch.zeros(tokens.ids.shape[0], dtype=torch.bool)
        for row, sequence in enumerate(tokens.sequences()):
            pieces = [encoding.id_to_token(token) for token in sequence]
            text = "".join(piece for piece in pieces if piece is not None)
            values = [ord(character) - ALPHABET_START + self.minimum for character in text]
            invalid[row] = None in pieces or len(values) != count
            coefficients[row, : min(count, len(values))] = values[:count]
        return DecodedChunks(self.chunks_of(coefficients), invalid)

    def save(self, directory: Path) -> None:
        """Write ``kind.json`` and the byte-pair encoding ``bpe.json``."""
        settings = {
            "action_dim": self.action_dim,
            "action_horizon": self.action_horizon,
            "scale": self.scale,
            "vocabulary_size": self.requested_vocabulary_size,
            "minimum": self.minimum,
            "maximum": self.maximum,
            "tokens_per_chunk": [self.lengths.mean, self.lengths.p95, self.lengths.maximum],
        }
        write_kind_file(directory, KIND, settings)
        write_text(Path(directory) / ENCODING_FILENAME, self._encoding().to_str())

    @classmethod
    def load(cls, directory: Path) -> "FastTokenizer":
        """Read a folder written by :meth:`save`."""
        settings = expect_kind(directory, KIND)
        tokenizer = cls(
            settings["action_dim"], settings["action_horizon"], settings["scale"], settings["vocabulary_size"]
        )
        tokenizer.minimum, tokenizer.maximum = settings["minimum"], settings["maximum"]
        mean, p95, maximum = settings["tokens_per_chunk"]
        tokenizer.lengths = TokensPerChunk(mean, p95, maximum)
        tokenizer.encoding = Tokenizer.from_str((Path(directory) / ENCODING_FILENAME).read_text())
        return tokenizer
