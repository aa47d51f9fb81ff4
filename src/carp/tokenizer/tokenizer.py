"""Multi-scale residual action tokenizer: one VQ-VAE per action dimension, computed for all A dimensions at once.

Sources: the multi-scale residual quantization of VAR (Tian et al. 2024, FoundationVision/VAR) applied per action
dimension as in CARP (Gong et al. 2024, ZhefeiGong/carp `MSAT/vqvae.py`, `svqvae/`); docs/architecture.md, "Action
tokenizer" and "Token layout and attention mask", summarizes both. The encoder/decoder and quantizer modules document
their own deviations; at this level the deviations are:

- The A per-dimension VQ-VAEs are one module with grouped convolutions and an (A, V, C) codebook instead of a Python
  list of A modules (same math; `carp.tokenizer.per_dimension` converts between the two forms).
- No `quant_conv` / `post_quant_conv` around the quantizer (the encoder's output conv and the decoder's input conv
  already map to and from C channels).
- Scale schedules of any length (the paper's Fig. 10 varies K from 1 to 6 with maps 1..K). The scales quantize a
  latent of length l = max(encoder length, s_K): a last scale shorter than the encoder's output reconstructs from
  coarser maps only (every scale's contribution is up-sampled to l, as in VAR), and a longer one gets a latent of its
  own length, the encoder's output bicubic-resampled up to it and the quantized latent area-resampled back before the
  decoder, so the round trip keeps its shapes whatever the schedule.
- The training loss sums the A per-dimension objectives (each a reconstruction MSE plus the VQ loss, both means
  over that dimension's elements), so every dimension receives exactly the gradients of an independent VQ-VAE.

Inputs are normalized actions in [-1, 1]; normalization happens in the data layer. Scale indices are 0-based
(`scale_index` k addresses `spec.scales[k]`).

Token layout of a chunk (docs/architecture.md, "Token layout and attention mask"): scale-major, then position, then
dimension, so scale k contributes s_k * A tokens ordered [pos0: d0..d(A-1), pos1: d0..d(A-1), ...] and token i of a
scale (and of the whole sequence, since every scale block is a multiple of A long) belongs to dimension i % A.
"""

from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from carp.tokenizer.autoencoder import ActionDecoder, ActionEncoder
from carp.tokenizer.quantizer import MultiScaleQuantizer
from carp.tokenizer.spec import TokenizerSpec

# 2: convolution weights are 4-D (out, in, 1, k) (were 3-D Conv1d weights in version 1).
TOKENIZER_FORMAT_VERSION = 2


@dataclass
class TokenizerOutput:
    """Result of a training forward pass.

    Attributes:
        reconstruction: (B, H, A) decoded normalized actions.
        loss: scalar objective to minimize, the sum over dimensions of reconstruction MSE + VQ loss.
        reconstruction_loss: scalar MSE over all elements (B, H, A), for logging.
        vq_loss: scalar VQ loss averaged over dimensions, for logging.
        token_ids: K tensors (B, A, s_k) long.
    """

    reconstruction: torch.Tensor
    loss: torch.Tensor
    reconstruction_loss: torch.Tensor
    vq_loss: torch.Tensor
    token_ids: list[torch.Tensor]


class MultiScaleActionTokenizer(nn.Module):
    """The A per-dimension multi-scale residual VQ-VAEs over action chunks, computed as one vectorized module.

    Args:
        spec: architecture (A, H, scales, V, C, channels, beta).
    """

    def __init__(self, spec: TokenizerSpec) -> None:
        super().__init__()
        self.spec = spec
        self.encoder = ActionEncoder(spec)
        self.quantizer = MultiScaleQuantizer(spec)
        self.decoder = ActionDecoder(spec)
        # The convolutions run on channels-last images (see `carp.tokenizer.autoencoder`); kernels stored in the same
        # layout spare oneDNN a reorder of every weight on every call.
        self.to(memory_format=torch.channels_last)

    def _check_actions(self, actions: torch.Tensor) -> None:
        expected = (self.spec.action_horizon, self.spec.action_dim)
        if actions.dim() != 3 or tuple(actions.shape[1:]) != expected:
            raise ValueError(
                f"actions must have shape (B, H, A) = (B, {expected[0]}, {expected[1]}), got {tuple(actions.shape)}"
            )

    def _check_token_ids(self, token_ids: list[torch.Tensor]) -> None:
        if len(token_ids) != self.spec.num_scales:
            raise ValueError(f"expected token ids for {self.spec.num_scales} scales, got {len(token_ids)}")
        for scale_index, ids in enumerate(token_ids):
            self._check_scale_ids(ids, scale_index)

    def _check_scale_ids(self, ids: torch.Tensor, scale_index: int) -> None:
        expected = (self.spec.action_dim, self.spec.scales[scale_index])
        if ids.dim() != 3 or tuple(ids.shape[1:]) != expected:
            raise ValueError(
                f"token ids of scale index {scale_index} must have shape (B, A, s_k) = (B, "
                f"{expected[0]}, {expected[1]}), got {tuple(ids.shape)}"
            )

    def forward(self, actions: torch.Tensor) -> TokenizerOutput:
        """Encode, quantize and decode a batch for training.

        Args:
            actions: (B, H, A) float normalized actions.

        Returns:
            TokenizerOutput with the reconstruction (B, H, A), losses and token ids (K tensors (B, A, s_k)).
        """
        self._check_actions(actions)
        latent = self.encode_to_latent(actions)  # (B, A, C, l)
        quantized, token_ids, vq_loss = self.quantizer.quantize(latent)
        reconstruction = self.decode_latent(quantized)  # (B, H, A)
        reconstruction_loss = F.mse_loss(reconstruction, actions)
        loss = self.spec.action_dim * (reconstruction_loss + vq_loss)
        return TokenizerOutput(reconstruction, loss, reconstruction_loss, vq_loss, token_ids)

    def encode_to_latent(self, actions: torch.Tensor) -> torch.Tensor:
        """Encode normalized actions (B, H, A) into continuous latents f (B, A, C, l), before quantization."""
        self._check_actions(actions)
        latent = self.encoder(rearrange(actions, "b h a -> b a 1 h"))  # (B, A * C, 1, encoder length)
        latent = rearrange(latent, "b (a c) 1 t -> b a c t", a=self.spec.action_dim)
        # A schedule whose last scale is longer than the encoder's output quantizes a latent of that length.
        return self.quantizer.resample(latent, self.spec.latent_length, mode="bicubic")  # (B, A, C, l)

    def encode_to_ids(self, actions: torch.Tensor) -> list[torch.Tensor]:
        """Tokenize normalized actions (B, H, A) into K token-id tensors (B, A, s_k) long."""
        with torch.no_grad():
            return self.quantizer.encode(self.encode_to_latent(actions))

    def ids_to_latent(self, token_ids: list[torch.Tensor]) -> torch.Tensor:
        """Accumulate f_hat (B, A, C, l) from the token ids of all K scales, each (B, A, s_k)."""
        self._check_token_ids(token_ids)
        batch_size = token_ids[0].shape[0]
        quantized = self.empty_latent(batch_size, device=token_ids[0].device)
        for scale_index, ids in enumerate(token_ids):
            quantized = self.embed_scale(quantized, ids, scale_index)
        return quantized

    def empty_latent(self, batch_size: int, device: torch.device | str | None = None) -> torch.Tensor:
        """The f_hat before any scale is embedded: zeros (B, A, C, l), time-major in memory like encoder latents."""
        spec = self.spec
        zeros = torch.zeros(
            batch_size,
            spec.latent_length,
            spec.action_dim,
            spec.latent_channels,
            device=device,
            dtype=self.quantizer.codebook.dtype,
        )
        return rearrange(zeros, "b t a c -> b a c t")

    def embed_scale(self, quantized: torch.Tensor, token_ids: torch.Tensor, scale_index: int) -> torch.Tensor:
        """Add scale k's contribution h_k to f_hat (one inference step).

        Args:
            quantized: f_hat accumulated over scales < k, (B, A, C, l).
            token_ids: scale k's ids, (B, A, s_k) long.
            scale_index: k, 0-based.

        Returns:
            f_hat + h_k, (B, A, C, l) (a new tensor; the input is not modified).
        """
        self._check_scale_ids(token_ids, scale_index)
        return quantized + self.quantizer.scale_contribution(token_ids, scale_index)

    def next_scale_input(self, quantized: torch.Tensor, scale_index: int) -> torch.Tensor:
        """Area-downsample f_hat (B, A, C, l), accumulated up to scale k, to (B, A, C, s_{k+1}).

        This is the transformer's input for predicting scale k + 1 (0-based `scale_index` = k < K - 1).
        """
        if not 0 <= scale_index < self.spec.num_scales - 1:
            raise ValueError(
                f"scale_index must be in [0, {self.spec.num_scales - 2}] (a next scale must exist), got {scale_index}"
            )
        return self.quantizer.resample(quantized, self.spec.scales[scale_index + 1], mode="area")

    def teacher_forcing_inputs(self, token_ids: list[torch.Tensor]) -> list[torch.Tensor]:
        """Inputs for predicting scales 2..K from ground-truth ids: K - 1 tensors (B, A, C, s_k), k = 2..K."""
        self._check_token_ids(token_ids)
        quantized = self.empty_latent(token_ids[0].shape[0], device=token_ids[0].device)
        inputs = []
        for scale_index in range(self.spec.num_scales - 1):
            quantized = self.embed_scale(quantized, token_ids[scale_index], scale_index)
            inputs.append(self.next_scale_input(quantized, scale_index))
        return inputs

    def decode_latent(self, quantized: torch.Tensor) -> torch.Tensor:
        """Decode f_hat (B, A, C, l) into normalized actions (B, H, A)."""
        quantized = self.quantizer.resample(quantized, self.spec.encoder_length, mode="area")  # the decoder's length
        image = rearrange(quantized, "b a c t -> b (a c) 1 t")
        return rearrange(self.decoder(image), "b a 1 h -> b h a")

    def decode_ids(self, token_ids: list[torch.Tensor]) -> torch.Tensor:
        """Decode K token-id tensors (B, A, s_k) into normalized actions (B, H, A)."""
        return self.decode_latent(self.ids_to_latent(token_ids))

    def ids_to_sequence(self, token_ids: list[torch.Tensor]) -> torch.Tensor:
        """Flatten K id tensors (B, A, s_k) into the chunk's token sequence (B, L), in the chunk's token layout."""
        self._check_token_ids(token_ids)
        return torch.cat([rearrange(ids, "b a s -> b (s a)") for ids in token_ids], dim=1)  # (B, L)

    def sequence_to_ids(self, sequence: torch.Tensor) -> list[torch.Tensor]:
        """Split a token sequence (B, L) back into K id tensors (B, A, s_k)."""
        spec = self.spec
        if sequence.dim() != 2 or sequence.shape[1] != spec.tokens_per_chunk:
            raise ValueError(
                f"token sequence must have shape (B, L) = (B, {spec.tokens_per_chunk}), got {tuple(sequence.shape)}"
            )
        blocks = torch.split(sequence, [scale * spec.action_dim for scale in spec.scales], dim=1)
        return [rearrange(block, "b (s a) -> b a s", a=spec.action_dim) for block in blocks]

    def teacher_forcing_sequence(self, token_ids: list[torch.Tensor]) -> torch.Tensor:
        """Teacher-forcing inputs of scales 2..K in sequence layout, (B, L - s_1 * A, C)."""
        inputs = self.teacher_forcing_inputs(token_ids)
        if not inputs:  # a single scale has nothing to teacher-force
            return torch.zeros(token_ids[0].shape[0], 0, self.spec.latent_channels, device=token_ids[0].device)
        return torch.cat([rearrange(latent, "b a c s -> b (s a) c") for latent in inputs], dim=1)

    def encode_to_sequence(self, actions: torch.Tensor) -> torch.Tensor:
        """Tokenize normalized actions (B, H, A) straight into the token sequence (B, L) long."""
        return self.ids_to_sequence(self.encode_to_ids(actions))

    def to_checkpoint(self) -> dict[str, Any]:
        """Self-describing state: format version, spec and weights (load with `from_checkpoint`)."""
        return {
            "format_version": TOKENIZER_FORMAT_VERSION,
            "spec": self.spec.to_dict(),
            "state_dict": self.state_dict(),
        }

    @classmethod
    def from_checkpoint(cls, checkpoint: dict[str, Any]) -> "MultiScaleActionTokenizer":
        """Rebuild a tokenizer from `to_checkpoint` output, loading weights strictly."""
        version = checkpoint.get("format_version")
        if version != TOKENIZER_FORMAT_VERSION:
            raise ValueError(
                f"tokenizer checkpoint has format_version {version!r}, this code reads version "
                f"{TOKENIZER_FORMAT_VERSION}"
            )
        tokenizer = cls(TokenizerSpec.from_dict(checkpoint["spec"]))
        tokenizer.load_state_dict(checkpoint["state_dict"], strict=True)
        return tokenizer
