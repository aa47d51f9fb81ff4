"""VQ-BeT's residual VQ over a whole chunk as a tokenizer kind: one code per residual layer.

The network and its training are the VQ-BeT family's (`carp.tokenizer.kinds.chunk_vqvae`): an MLP encoder maps a
normalized chunk (H x A values together) to one latent, each of R residual layers quantizes what the layers before
it left over with its own codebook of N codes (EMA updates), and an MLP decoder maps the sum of the chosen codes back
to the chunk. Token layout: the R codes coarse to fine, L = R; every layer's ids are in [0, N), so V = N and a
token's position tells its codebook. Bits per chunk: R x log2 N (VQ-BeT's 2 layers of 16 codes: 8).

As a tokenizer the kind has no offsets: VQ-BeT's policy adds a predicted continuous offset to the decoded chunk, a
kind's round trip is the decoded chunk alone, so its distortion is that of the codes and R and N are its rate knob.
"""

import dataclasses
from pathlib import Path

import torch

from carp.tokenizer.kinds.base import DecodedChunks, TokenBatch, TokensPerChunk, check_chunks
from carp.tokenizer.kinds.bins import repaired_ids
from carp.tokenizer.kinds.chunk_vqvae import ActionAutoencoder, AutoencoderShape, AutoencoderTraining, train_autoencoder
from carp.tokenizer.kinds.joint_network import load_network, save_network

KIND = "residual_vq"


class ResidualVqTokenizer:
    """A trained :class:`~carp.tokenizer.kinds.chunk_vqvae.ActionAutoencoder`: one token per residual layer.

    Args:
        action_dim: A.
        action_horizon: H.
        num_layers: R, residual layers (tokens per chunk).
        num_codes: N, codes per layer (the vocabulary).
        latent_width: width of the latent and of every code.
        hidden_width: width of the encoder's and decoder's hidden layers.
        codebook_decay: EMA decay of the codebooks per step, in (0, 1).
        commitment_weight: weight of the commitment loss (summed over layers) next to the L1 reconstruction.
        steps: Adam steps of ``fit``.
        batch_size: windows per step.
        learning_rate: Adam's learning rate.
        weight_decay: Adam's (L2) weight decay.
        seed: seeds the initialization, the codebooks' first codes and the batches.
    """

    kind = KIND

    def __init__(
        self,
        action_dim: int,
        action_horizon: int,
        num_layers: int = 2,
        num_codes: int = 16,
        latent_width: int = 256,
        hidden_width: int = 128,
        codebook_decay: float = 0.8,
        commitment_weight: float = 5.0,
        steps: int = 20000,
        batch_size: int = 256,
        learning_rate: float = 1e-3,
        weight_decay: float = 1e-4,
        seed: int = 0,
    ) -> None:
        self.action_dim, self.action_horizon = action_dim, action_horizon
        self.shape = AutoencoderShape(
            action_horizon, action_dim, hidden_width, latent_width, num_layers, num_codes, codebook_decay
        )
        self.training = AutoencoderTraining(steps, batch_size, learning_rate, weight_decay, commitment_weight, seed)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.module = ActionAutoencoder(self.shape).eval().requires_grad_(False)

    @classmethod
    def from_config(cls, config, action_dim: int, action_horizon: int) -> "ResidualVqTokenizer":
        """Built from a `carp.config.tokenizer_kinds.ResidualVqConfig`."""
        return cls(action_dim, action_horizon, **dataclasses.asdict(config))

    @property
    def vocabulary_size(self) -> int:
        """V = N, the codes of one layer."""
        return self.shape.num_codes

    @property
    def tokens_per_chunk(self) -> TokensPerChunk:
        """L = R."""
        return TokensPerChunk.fixed(self.shape.num_layers)

    def fit(self, windows: torch.Tensor) -> None:
        """Train the VQ-VAE on windows (N, H, A) as VQ-BeT's first phase does, then freeze it."""
        check_chunks(windows, self.action_horizon, self.action_dim)
        train_autoencoder(self.module, windows.float(), self.training)

    def encode(self, chunks: torch.Tensor) -> TokenBatch:
        """(B, R) token ids of chunks (B, H, A): each layer's code for what the layers before it left."""
        check_chunks(chunks, self.action_horizon, self.action_dim)
        with torch.inference_mode():
            return TokenBatch.fixed(self.module.encode_to_ids(chunks.float()))

    def decode(self, tokens: TokenBatch) -> DecodedChunks:
        """Chunks (B, H, A); ids outside [0, N) or rows of another length are repaired and flagged."""
        ids, invalid = repaired_ids(tokens, self.shape.num_layers, self.vocabulary_size)
        with torch.inference_mode():
            return DecodedChunks(self.module.decode_ids(ids), invalid)

    def save(self, directory: Path) -> None:
        """Write ``kind.json`` and the weights and codebooks ``weights.pt``."""
        shape, training = self.shape, self.training
        settings = {
            "action_dim": self.action_dim,
            "action_horizon": self.action_horizon,
            "num_layers": shape.num_layers,
            "num_codes": shape.num_codes,
            "latent_width": shape.latent_width,
            "hidden_width": shape.hidden_width,
            "codebook_decay": shape.codebook_decay,
            "commitment_weight": training.commitment_weight,
            "steps": training.steps,
            "batch_size": training.batch_size,
            "learning_rate": training.learning_rate,
            "weight_decay": training.weight_decay,
            "seed": training.seed,
        }
        save_network(directory, KIND, settings, self.module)

    @classmethod
    def load(cls, directory: Path) -> "ResidualVqTokenizer":
        """Read a folder written by :meth:`save`, loading the weights and codebooks strictly."""
        return load_network(directory, KIND, lambda settings: cls(**settings), ())
