"""A multi-scale residual VQ-VAE over all action dimensions jointly: the design CARP's paper argues against.

CARP tokenizes each dimension with its own VQ-VAE (`carp_msvq`); its supplementary (Fig. 6) reports one VAR-style
multi-scale VQ-VAE over all dimensions as unstable. This kind is that alternative, built from the same quantizer
(`carp.tokenizer.quantizer.MultiScaleQuantizer` with a single "dimension": one codebook of V codes of C channels,
the same scales, phi convolutions and resampling) behind a small joint convolutional encoder and decoder
(`carp.tokenizer.kinds.joint_network`) that see all A dimensions as channels. Token layout: scale-major, then
position; L = s_1 + ... + s_K, V = ``codebook_size``.

Training is Adam on the reconstruction MSE plus the quantizer's VQ loss, with the codebook initialized from encoder
residuals and codes unused over an interval re-seeded during the first quarter of the steps (as
`carp.training.tokenizer_trainer` does per dimension, in a simpler loop without warm-up, augmentation or resuming).
"""

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from carp.tokenizer.kinds.base import (
    DecodedChunks,
    TokenBatch,
    TokensPerChunk,
    check_chunks,
)
from carp.tokenizer.kinds.bins import repaired_ids
from carp.tokenizer.kinds.joint_network import fit_by_adam, load_network, save_network, temporal_convolutions
from carp.tokenizer.metrics import count_codes
from carp.tokenizer.quantizer import MultiScaleQuantizer
from carp.tokenizer.spec import TokenizerSpec

KIND = "joint_msvq"
RESTART_INTERVALS = 10
"""Code restarts happen every ``steps / RESTART_INTERVALS`` steps, within the first quarter of training."""


class JointMsvqAutoencoder(nn.Module):
    """Joint encoder, one multi-scale residual quantizer, joint decoder.

    Args:
        spec: the quantizer's settings, with ``action_dim`` 1 (one codebook) and ``2 ** len(channel_mult)`` the
            encoder's downsampling.
        action_dim: A, the channels of the encoder's input and the decoder's output.
        hidden_channels: width of the convolutions.
    """

    def __init__(self, spec: TokenizerSpec, action_dim: int, hidden_channels: int) -> None:
        super().__init__()
        self.spec = spec
        halvings = len(spec.channel_mult)
        self.encoder = temporal_convolutions(action_dim, hidden_channels, spec.latent_channels, halvings, False)
        self.quantizer = MultiScaleQuantizer(spec)
        self.decoder = temporal_convolutions(spec.latent_channels, hidden_channels, action_dim, halvings, True)

    def encode_to_latent(self, chunks: torch.Tensor) -> torch.Tensor:
        """The latent f (1 quantizer "dimension"), (B, 1, C, l), of chunks (B, H, A)."""
        latent = self.encoder(rearrange(chunks, "b h a -> b a h"))  # (B, C, H / downsampling)
        # The quantizer keeps latents time-major in memory (see `carp.tokenizer.quantizer`).
        latent = rearrange(rearrange(latent, "b c t -> b t c").contiguous(), "b t c -> b 1 c t")
        return self.quantizer.resample(latent, self.spec.latent_length, mode="bicubic")

    def decode_latent(self, quantized: torch.Tensor) -> torch.Tensor:
        """Chunks (B, H, A) of a quantized latent (B, 1, C, l)."""
        quantized = self.quantizer.resample(quantized, self.spec.encoder_length, mode="area")
        return rearrange(self.decoder(rearrange(quantized, "b 1 c t -> b c t")), "b a h -> b h a")

    def ids_to_latent(self, token_ids: list[torch.Tensor]) -> torch.Tensor:
        """f_hat (B, 1, C, l) accumulated from K id tensors (B, 1, s_k)."""
        batch_size = token_ids[0].shape[0]
        quantized = torch.zeros(batch_size, 1, self.spec.latent_channels, self.spec.latent_length)
        for scale_index, ids in enumerate(token_ids):
            quantized = quantized + self.quantizer.scale_contribution(ids, scale_index)
        return quantized


class JointMsvqTokenizer:
    """A trained :class:`JointMsvqAutoencoder`.

    Args:
        action_dim: A.
        action_horizon: H, divisible by ``downsampling``.
        scales: s_1..s_K, tokens per chunk at each scale; strictly increasing, the last at most H.
        codebook_size: V.
        latent_channels: C, width of a code.
        downsampling: the encoder's temporal downsampling, a power of two >= 2.
        hidden_channels: width of the convolutions.
        commitment_weight: beta of the VQ loss.
        steps: Adam steps of ``fit``.
        batch_size: windows per step.
        learning_rate: Adam's learning rate.
        seed: seeds initialization, batches and code restarts.
    """

    kind = KIND

    def __init__(
        self,
        action_dim: int,
        action_horizon: int,
        scales: tuple[int, ...] = (1, 2, 3, 4),
        codebook_size: int = 512,
        latent_channels: int = 8,
        downsampling: int = 4,
        hidden_channels: int = 32,
        commitment_weight: float = 0.25,
        steps: int = 2000,
        batch_size: int = 256,
        learning_rate: float = 1e-3,
        seed: int = 0,
    ) -> None:
        if downsampling < 2 or downsampling & (downsampling - 1):
            raise ValueError(f"downsampling must be a power of two >= 2, got {downsampling}")
        self.action_dim, self.action_horizon = action_dim, action_horizon
        self.settings = {
            "scales": list(scales),
            "codebook_size": codebook_size,
            "latent_channels": latent_channels,
            "downsampling": downsampling,
            "hidden_channels": hidden_channels,
            "commitment_weight": commitment_weight,
            "steps": steps,
            "batch_size": batch_size,
            "learning_rate": learning_rate,
            "seed": seed,
        }
        spec = TokenizerSpec(
            action_dim=1,
            action_horizon=action_horizon,
            scales=tuple(scales),
            codebook_size=codebook_size,
            latent_channels=latent_channels,
            channel_mult=(1,) * int(math.log2(downsampling)),
            commitment_weight=commitment_weight,
        )
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.module = JointMsvqAutoencoder(spec, action_dim, hidden_channels).eval()

    @classmethod
    def from_config(cls, config, action_dim: int, action_horizon: int) -> "JointMsvqTokenizer":
        """Built from a `carp.config.tokenizer_kinds.JointMsvqConfig`."""
        return cls(
            action_dim,
            action_horizon,
            config.scales,
            config.codebook_size,
            config.latent_channels,
            config.downsampling,
            config.hidden_channels,
            config.commitment_weight,
            config.steps,
            config.batch_size,
            config.learning_rate,
            config.seed,
        )

    @property
    def vocabulary_size(self) -> int:
        """V = ``codebook_size``."""
        return self.module.spec.codebook_size

    @property
    def tokens_per_chunk(self) -> TokensPerChunk:
        """L = s_1 + ... + s_K."""
        return TokensPerChunk.fixed(sum(self.module.spec.scales))

    def fit(self, windows: torch.Tensor) -> None:
        """Train on windows (N, H, A): reconstruction MSE plus VQ loss, codes seeded and re-seeded from residuals."""
        check_chunks(windows, self.action_horizon, self.action_dim)
        module, settings = self.module, self.settings
        windows = windows.float()
        generator = torch.Generator().manual_seed(settings["seed"])
        usage = torch.zeros(1, self.vocabulary_size, dtype=torch.long)

        def restart(unused: torch.Tensor) -> None:
            sample = windows[torch.randperm(len(windows), generator=generator)[:1024]]
            with torch.no_grad():
                candidates = module.quantizer.residual_vectors(module.encode_to_latent(sample))  # (1, n, C)
            module.quantizer.restart_codes(unused, candidates, generator)

        def loss_of_batch(batch: torch.Tensor) -> torch.Tensor:
            quantized, token_ids, vq_loss = module.quantizer.quantize(module.encode_to_latent(batch))
            for ids in token_ids:
                usage.add_(count_codes(ids, self.vocabulary_size))
            return F.mse_loss(module.decode_latent(quantized), batch) + vq_loss

        interval = max(1, settings["steps"] // RESTART_INTERVALS)

        def after_step(step: int) -> None:
            if (step + 1) % interval == 0:
                if step < settings["steps"] // 4:
                    restart(usage == 0)
                usage.zero_()

        restart(torch.ones(1, self.vocabulary_size, dtype=torch.bool))
        fit_by_adam(
            module,
            windows,
            loss_of_batch,
            settings["steps"],
            settings["batch_size"],
            settings["learning_rate"],
            settings["seed"],
            after_step,
        )

    def encode(self, chunks: torch.Tensor) -> TokenBatch:
        """(B, L) ids of chunks (B, H, A), scale-major."""
        check_chunks(chunks, self.action_horizon, self.action_dim)
        with torch.inference_mode():
            token_ids = self.module.quantizer.encode(self.module.encode_to_latent(chunks.float()))
        return TokenBatch.fixed(torch.cat([ids[:, 0] for ids in token_ids], dim=1))

    def decode(self, tokens: TokenBatch) -> DecodedChunks:
        """Chunks (B, H, A); ids outside [0, V) or rows of another length are repaired and flagged."""
        ids, invalid = repaired_ids(tokens, self.tokens_per_chunk.maximum, self.vocabulary_size)
        token_ids = [block[:, None] for block in torch.split(ids, list(self.module.spec.scales), dim=1)]
        with torch.inference_mode():
            return DecodedChunks(self.module.decode_latent(self.module.ids_to_latent(token_ids)), invalid)

    def save(self, directory: Path) -> None:
        """Write ``kind.json`` and the weights ``weights.pt``."""
        settings = {"action_dim": self.action_dim, "action_horizon": self.action_horizon, **self.settings}
        save_network(directory, KIND, settings, self.module)

    @classmethod
    def load(cls, directory: Path) -> "JointMsvqTokenizer":
        """Read a folder written by :meth:`save`, loading the weights strictly."""
        return load_network(directory, KIND, lambda settings: cls(**settings), ("scales",))
