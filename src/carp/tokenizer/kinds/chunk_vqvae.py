"""VQ-BeT's action tokenizer: an MLP VQ-VAE over whole action chunks, with a residual quantizer between.

An encoder maps a chunk of H actions (normalized, flattened to H * A values) to one latent, the residual quantizer
(`carp.tokenizer.kinds.residual_quantizer`) turns it into one code per layer, and a decoder maps the quantized latent
back to the chunk. Trained on L1 reconstruction plus a weighted commitment loss, with Adam. Two users: the VQ-BeT
family (`carp.policies.vq_bet`) trains one before its GPT, freezes it and keeps it in the policy's checkpoint; the
`residual_vq` tokenizer kind (`carp.tokenizer.kinds.residual_vq`) trains one on the pipeline's training windows and
serves its codes as tokens to the next-token family.

Source: Lee et al., "Behavior Generation with Latent Actions" (ICML 2024) and its public code (`vqvae.py`: MLP
encoder and decoder with 128-wide hidden layers, the L1 reconstruction plus 5 times the quantizer's commitment loss,
and the quantizer package's EMA decay of 0.8, which the defaults of `carp.config.tokenizer_kinds.ResidualVqConfig`
follow). Deviations: the chunk is the pipeline's horizon H rather than VQ-BeT's per-timestep window; training runs a
fixed number of steps on batches drawn with a seeded generator.
"""

import logging
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn
from tqdm.auto import tqdm

from carp.tokenizer.kinds.residual_quantizer import ResidualVectorQuantizer

logger = logging.getLogger(__name__)


def multilayer_perceptron(input_width: int, hidden_width: int, output_width: int) -> nn.Sequential:
    """Three Linear layers with ReLU between them: input -> hidden -> hidden -> output (VQ-BeT's MLP shape)."""
    return nn.Sequential(
        nn.Linear(input_width, hidden_width),
        nn.ReLU(),
        nn.Linear(hidden_width, hidden_width),
        nn.ReLU(),
        nn.Linear(hidden_width, output_width),
    )


@dataclass(frozen=True)
class AutoencoderShape:
    """Sizes of an :class:`ActionAutoencoder`, as its checkpoint stores them.

    Attributes:
        action_horizon: `H`, actions per chunk.
        action_dim: `A`.
        hidden_width: width of the encoder's and decoder's hidden layers.
        latent_width: width of the latent and of every code.
        num_layers: residual quantizer layers (codes per chunk).
        num_codes: codes per layer.
        codebook_decay: EMA decay of the codebooks, in (0, 1).
    """

    action_horizon: int
    action_dim: int
    hidden_width: int
    latent_width: int
    num_layers: int
    num_codes: int
    codebook_decay: float


class ActionAutoencoder(nn.Module):
    """MLP encoder, residual quantizer and MLP decoder over one (H, A) action chunk.

    Args:
        shape: its sizes.
    """

    def __init__(self, shape: AutoencoderShape) -> None:
        super().__init__()
        self.shape = shape
        chunk_width = shape.action_horizon * shape.action_dim
        self.encoder = multilayer_perceptron(chunk_width, shape.hidden_width, shape.latent_width)
        self.quantizer = ResidualVectorQuantizer(
            shape.num_layers, shape.num_codes, shape.latent_width, shape.codebook_decay
        )
        self.decoder = multilayer_perceptron(shape.latent_width, shape.hidden_width, chunk_width)

    def encode_to_latent(self, actions: torch.Tensor) -> torch.Tensor:
        """(N, H, A) normalized chunks -> (N, latent_width) latents before quantization."""
        return self.encoder(rearrange(actions, "n h a -> n (h a)"))

    def encode_to_ids(self, actions: torch.Tensor) -> torch.Tensor:
        """(N, H, A) normalized chunks -> (N, num_layers) long code ids."""
        return self.quantizer.encode_to_ids(self.encode_to_latent(actions))

    def decode_latent(self, latent: torch.Tensor) -> torch.Tensor:
        """(N, latent_width) quantized latents -> (N, H, A) normalized chunks."""
        return rearrange(self.decoder(latent), "n (h a) -> n h a", h=self.shape.action_horizon)

    def decode_ids(self, code_ids: torch.Tensor) -> torch.Tensor:
        """(N, num_layers) long code ids -> (N, H, A) normalized chunks."""
        return self.decode_latent(self.quantizer.ids_to_latent(code_ids))

    def losses(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(L1 reconstruction, commitment) scalar losses of a batch of (N, H, A) chunks; updates the codebooks."""
        quantized, _, commitment = self.quantizer(self.encode_to_latent(actions))
        reconstruction = F.l1_loss(self.decode_latent(quantized), actions)
        return reconstruction, commitment


@dataclass(frozen=True)
class AutoencoderTraining:
    """How :func:`train_autoencoder` trains.

    Attributes:
        steps: Adam steps.
        batch_size: chunks per step.
        learning_rate: Adam learning rate.
        weight_decay: Adam (L2) weight decay.
        commitment_weight: weight of the commitment loss (summed over layers) next to the L1 reconstruction.
        seed: seeds the codebook initialization and the batch draws.
    """

    steps: int
    batch_size: int
    learning_rate: float
    weight_decay: float
    commitment_weight: float
    seed: int


def train_autoencoder(autoencoder: ActionAutoencoder, actions: torch.Tensor, training: AutoencoderTraining) -> None:
    """Fit `autoencoder` to the (N, H, A) normalized chunks in place, then freeze it (eval mode, no gradients).

    Deterministic given `training.seed` and the weights it starts from: the codebooks start from encoded chunks of a
    first seeded batch, and every batch is drawn with the same seeded generator.
    """
    if training.steps < 1 or training.batch_size < 1:
        raise ValueError(f"need steps >= 1 and batch_size >= 1, got {training.steps}, {training.batch_size}")
    device = actions.device
    generator = torch.Generator().manual_seed(training.seed)
    count = actions.shape[0]
    # A policy holds its VQ-VAE frozen; this phase is the one that trains it.
    autoencoder.train().requires_grad_(True)
    with torch.no_grad():
        first = torch.randint(count, (max(training.batch_size, autoencoder.shape.num_codes),), generator=generator)
        autoencoder.quantizer.initialize(autoencoder.encode_to_latent(actions[first.to(device)]), generator)
    optimizer = torch.optim.Adam(
        autoencoder.parameters(), lr=training.learning_rate, weight_decay=training.weight_decay
    )
    progress = tqdm(range(training.steps), desc="residual VQ-VAE", leave=False)
    for step in progress:
        rows = torch.randint(count, (training.batch_size,), generator=generator).to(device)
        reconstruction, commitment = autoencoder.losses(actions[rows])
        loss = reconstruction + training.commitment_weight * commitment
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if step % 100 == 0:
            progress.set_postfix(l1=f"{reconstruction.item():.4f}")
    logger.info("residual VQ-VAE after %d steps: l1=%.4g", training.steps, float(reconstruction.detach()))
    autoencoder.eval().requires_grad_(False)
