"""Multi-scale residual vector quantization of per-dimension latents, vectorized over the A action dimensions.

Algorithm of VAR (Tian et al. 2024, FoundationVision/VAR `models/quant.py`) in one dimension, as CARP applies it to
action latents (ZhefeiGong/carp `svqvae/quant.py`): with residual r = f and f_hat = 0, for each scale k pick the
codes nearest (cosine similarity) to area-downsample(r, s_k), up-sample their embeddings back to l, refine them with
phi_k, and add the result h_k to f_hat while subtracting it from r.

Vectorization: one codebook parameter (A, V, C) and one grouped convolution per phi, so the A quantizers run in one
pass; tensors at this module's boundary are (B, A, C, T). Latents coming from the encoder are time-major in memory
((B, T, A, C), see `carp.tokenizer.autoencoder`) and every operation here keeps that layout, so the reshapes between
(B, A, C, T), the phi convs' (B, A * C, 1, T) images and the search's (A, B * T, C) rows are views, not copies.

Deviations from VAR/CARP:
- Phi convolutions are 1-D over time and grouped per dimension; the number of phi convs is fixed at 4.
- Relative-depth ties between two phi convs (e.g. the middle scale when K = 3) go to the coarser conv, decided in
  exact arithmetic rather than by floating-point rounding.
- Code embeddings are up-sampled with bicubic interpolation along time (as in VAR and CARP, through a singleton
  width axis); a single code (s_k = 1) up-samples to a constant. Both resamplings (area down, bicubic up) are applied
  as small precomputed matrices built by `F.interpolate` itself, which is the same linear map at a fraction of the
  CPU cost.
- The nearest-code search ranks codes by r . c / |c|, which orders them exactly as the cosine similarity does for a
  non-zero residual r, and normalizes the codebook once per pass instead of once per scale.
- No usage EMA buffers: codebook usage is measured from token ids by `carp.tokenizer.metrics` and the trainer.
- `restart_codes` re-seeds unused codes from encoder residuals (not part of VAR/CARP; see the trainer).
"""

from fractions import Fraction

import numpy as np
import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from carp.tokenizer.autoencoder import grouped_conv
from carp.tokenizer.spec import TokenizerSpec

NUM_PHI_CONVS = 4
PHI_RESIDUAL_RATIO = 0.5
# Similarities computed at once by the nearest-code search (4 MB of float32), see `nearest_codes`.
SEARCH_BLOCK_ELEMENTS = 1 << 20


def phi_index_for_scale(scale_index: int, num_scales: int, num_phi_convs: int = NUM_PHI_CONVS) -> int:
    """Pick the phi conv whose tick is nearest to the scale's relative depth k / (K - 1) (VAR's partial sharing).

    Ticks are evenly spaced in [1 / (3 n), 1 - 1 / (3 n)] for n = 4 convs (VAR's choice), else [1 / (2 n), 1 -
    1 / (2 n)]. With K = 4 scales and 4 convs every scale gets its own conv.
    """
    if num_phi_convs == 1:
        return 0
    depth = Fraction(scale_index, num_scales - 1) if num_scales > 1 else Fraction(0)
    margin = Fraction(1, 3 * num_phi_convs) if num_phi_convs == 4 else Fraction(1, 2 * num_phi_convs)
    step = (1 - 2 * margin) / (num_phi_convs - 1)
    distances = [abs(margin + index * step - depth) for index in range(num_phi_convs)]
    return distances.index(min(distances))


def resampling_matrix(source_length: int, target_length: int, mode: str) -> torch.Tensor:
    """The (target, source) matrix of `F.interpolate` along time with `mode` ("area" or "bicubic").

    Interpolation is linear in its input, so interpolating the identity gives its matrix. Applying the matrix with one
    small matmul is the same map as calling `F.interpolate`, several times cheaper on CPU for these short sequences
    (bicubic runs through a 2-D kernel with a singleton width axis, as in VAR and CARP; align_corners=False).
    """
    identity = torch.eye(source_length, dtype=torch.float64)[None]  # (1, source as channels, source as time)
    if mode == "area":
        columns = F.interpolate(identity, size=target_length, mode="area")
    elif mode == "bicubic":
        columns = F.interpolate(identity[..., None], size=(target_length, 1), mode="bicubic", align_corners=False)
        columns = columns[..., 0]
    else:
        raise ValueError(f"resampling mode must be 'area' or 'bicubic', got {mode!r}")
    return columns[0].T.float().contiguous()  # (target, source)


def first_maximum_indices(scores: torch.Tensor) -> torch.Tensor:
    """Index (...) long of the largest entry along the last axis of (..., V) scores, the first one on ties.

    On the CPU through NumPy, whose argmax is SIMD-vectorized along a contiguous axis: on (2, 256, 512) float32 scores
    (one search block) several times faster than `torch.max(...).indices` or `torch.argmax` on one thread, in a
    search that is a sizeable part of a tokenizer training step. Scores must not need grad.
    """
    if scores.device.type == "cpu" and scores.dtype == torch.float32:
        return torch.from_numpy(np.argmax(scores.contiguous().numpy(), axis=-1))
    return scores.max(dim=-1).indices


def _to_image(latent: torch.Tensor) -> torch.Tensor:
    """(B, A, C, T) -> (B, A * C, 1, T), the layout of `carp.tokenizer.autoencoder` (a view if time-major)."""
    return rearrange(latent, "b a c t -> b (a c) 1 t")


def _from_image(image: torch.Tensor, num_dimensions: int) -> torch.Tensor:
    """Inverse of `_to_image`: (B, A * C, 1, T) -> (B, A, C, T)."""
    return rearrange(image, "b (a c) 1 t -> b a c t", a=num_dimensions)


class MultiScaleQuantizer(nn.Module):
    """The A multi-scale residual quantizers (one per action dimension), computed in one pass.

    Args:
        spec: tokenizer architecture; uses A, V, C, the scales and beta.
    """

    def __init__(self, spec: TokenizerSpec) -> None:
        super().__init__()
        self.spec = spec
        num_dimensions, codebook_size = spec.action_dim, spec.codebook_size
        # Small uniform init as in VAR (vocab_init -1); the trainer replaces it with encoder residuals before
        # the first step.
        self.codebook = nn.Parameter(
            torch.empty(num_dimensions, codebook_size, spec.latent_channels).uniform_(
                -1.0 / codebook_size, 1.0 / codebook_size
            )
        )  # (A, V, C)
        self.phi_convs = nn.ModuleList(
            grouped_conv(num_dimensions, spec.latent_channels, spec.latent_channels) for _ in range(NUM_PHI_CONVS)
        )
        self.phi_of_scale = tuple(phi_index_for_scale(index, spec.num_scales) for index in range(spec.num_scales))
        # Interpolation matrices keyed by (source length, target length, mode, device, dtype), built on first use.
        self._resampling_matrices: dict[tuple, torch.Tensor] = {}

    def resample(self, latent: torch.Tensor, size: int, mode: str) -> torch.Tensor:
        """Resample (B, A, C, T) along time to time-major (B, A, C, size); `mode` is "area" (down) or "bicubic" (up)."""
        source_length = int(latent.shape[-1])  # a plain int, also where an ONNX trace records sizes as tensors
        if source_length == size:
            return latent
        key = (source_length, size, mode, latent.device, latent.dtype)
        matrix = self._resampling_matrices.get(key)
        if matrix is None:
            matrix = resampling_matrix(source_length, size, mode).to(device=latent.device, dtype=latent.dtype)
            self._resampling_matrices[key] = matrix
        batch, num_dimensions = latent.shape[:2]
        # One (size, T) x (T, B * A * C) product: a matmul broadcast over the batch runs B tiny products instead, whose
        # backward is slower at training batch sizes. The two small copies keep the result time-major.
        columns = rearrange(latent, "b a c t -> t b (a c)").reshape(source_length, -1)  # (T, B * A * C)
        resampled = (matrix @ columns).view(size, batch, -1).transpose(0, 1).contiguous()  # (B, size, A * C)
        return rearrange(resampled, "b s (a c) -> b a c s", a=num_dimensions)

    def unit_codebook(self) -> torch.Tensor:
        """The codes scaled to unit length (A, V, C), detached: what the nearest-code search compares against."""
        return F.normalize(self.codebook.detach(), dim=-1)

    def nearest_codes(self, residual: torch.Tensor, unit_codes: torch.Tensor | None = None) -> torch.Tensor:
        """Return ids (B, A, s) of each dimension's code with the highest cosine similarity to residual (B, A, C, s).

        Args:
            residual: (B, A, C, s) vectors to quantize.
            unit_codes: `unit_codebook()`, passed in by callers that search several scales with one codebook.
        """
        if unit_codes is None:
            unit_codes = self.unit_codebook()
        batch_size = residual.shape[0]
        # Dividing r . c_v by |r| would not change which code wins, so the residual is not normalized.
        queries = rearrange(residual.detach(), "b a c s -> a (b s) c")
        # The (A, B * s, V) similarities are the largest tensor of a training step (5 MB at A = 10, B = 64, s = 4);
        # searching a few dimensions at a time bounds that memory for any A. The block size hardly moves the step
        # time, so it is chosen for memory.
        dimensions_per_block = max(1, SEARCH_BLOCK_ELEMENTS // (queries.shape[1] * unit_codes.shape[1]))
        ids = [
            first_maximum_indices(torch.bmm(block_queries, block_codes.transpose(1, 2)))  # (dimensions, B * s)
            for block_queries, block_codes in zip(
                queries.split(dimensions_per_block), unit_codes.split(dimensions_per_block), strict=True
            )
        ]
        return rearrange(torch.cat(ids), "a (b s) -> b a s", b=batch_size)

    def code_vectors(self, token_ids: torch.Tensor) -> torch.Tensor:
        """Look up ids (B, A, s) in each dimension's own codebook, giving embeddings (B, A, C, s) (time-major)."""
        num_dimensions, codebook_size, _ = self.codebook.shape
        offsets = torch.arange(num_dimensions, device=token_ids.device) * codebook_size
        flat_ids = (rearrange(token_ids, "b a s -> b s a") + offsets).reshape(-1)  # rows of the (A * V, C) codebooks
        # index_select rather than F.embedding: same values, and its backward (an index_add) took half the time of
        # embedding's at A = 10, B = 64 on one CPU thread (170 against 315 us forward + backward at s = 4).
        vectors = self.codebook.reshape(num_dimensions * codebook_size, -1).index_select(0, flat_ids)  # (B*s*A, C)
        return rearrange(vectors, "(b s a) c -> b a c s", b=token_ids.shape[0], a=num_dimensions)

    def phi(self, scale_index: int, hidden: torch.Tensor) -> torch.Tensor:
        """phi_k(h) = (1 - 0.5) h + 0.5 conv_k3(h) on (B, A, C, l), with the conv shared by relative depth."""
        conv = self.phi_convs[self.phi_of_scale[scale_index]]
        image = _to_image(hidden)  # (B, A * C, 1, l)
        return _from_image(torch.lerp(image, conv(image), PHI_RESIDUAL_RATIO), self.spec.action_dim)

    def scale_contribution(self, token_ids: torch.Tensor, scale_index: int) -> torch.Tensor:
        """h_k = phi_k(upsample(E[z_k], l)): the latent (B, A, C, l) that scale k's ids (B, A, s_k) add to f_hat."""
        vectors = self.code_vectors(token_ids)  # (B, A, C, s_k)
        return self.phi(scale_index, self.resample(vectors, self.spec.latent_length, mode="bicubic"))

    def quantize(self, latent: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor], torch.Tensor]:
        """Quantize encoder latents over all scales (training path).

        Args:
            latent: f, (B, A, C, l) float encoder output.

        Returns:
            f_hat with the straight-through gradient (values of the quantized latent, gradient of f), (B, A, C, l);
            token ids per scale, K tensors (B, A, s_k) long; the VQ loss (scalar, mean over elements and scales):
            codebook term ||f_hat - sg(f)||^2 + beta * commitment term ||sg(f_hat) - f||^2, as VAR computes it on
            the running f_hat after every scale.
        """
        target = latent.detach()
        residual = target.clone()
        quantized = torch.zeros_like(target)
        token_ids = []
        vq_loss = latent.new_zeros(())
        unit_codes = self.unit_codebook()
        for scale_index, scale in enumerate(self.spec.scales):
            ids = self.nearest_codes(self.resample(residual, scale, mode="area"), unit_codes)  # (B, A, s_k)
            contribution = self.scale_contribution(ids, scale_index)  # (B, A, C, l)
            quantized = quantized + contribution
            residual = residual - contribution.detach()
            token_ids.append(ids)
            vq_loss = vq_loss + F.mse_loss(quantized, target)
            vq_loss = vq_loss + self.spec.commitment_weight * F.mse_loss(quantized.detach(), latent)
        vq_loss = vq_loss / self.spec.num_scales
        straight_through = latent + (quantized - latent).detach()
        return straight_through, token_ids, vq_loss

    @torch.no_grad()
    def encode(self, latent: torch.Tensor) -> list[torch.Tensor]:
        """Token ids per scale, K tensors (B, A, s_k) long, of latents (B, A, C, l)."""
        residual = latent.clone()
        token_ids = []
        unit_codes = self.unit_codebook()
        for scale_index, scale in enumerate(self.spec.scales):
            ids = self.nearest_codes(self.resample(residual, scale, mode="area"), unit_codes)
            residual = residual - self.scale_contribution(ids, scale_index)
            token_ids.append(ids)
        return token_ids

    @torch.no_grad()
    def residual_vectors(self, latent: torch.Tensor) -> torch.Tensor:
        """Collect the vectors the nearest-code search sees at every scale, (A, B * sum(s_k), C).

        These are the residuals a code must match, so they are the natural seeds for unused codes.
        """
        residual = latent.clone()
        collected = []
        unit_codes = self.unit_codebook()
        for scale_index, scale in enumerate(self.spec.scales):
            downsampled = self.resample(residual, scale, mode="area")  # (B, A, C, s_k)
            ids = self.nearest_codes(downsampled, unit_codes)
            residual = residual - self.scale_contribution(ids, scale_index)
            collected.append(rearrange(downsampled, "b a c s -> a (b s) c"))
        return torch.cat(collected, dim=1)

    @torch.no_grad()
    def restart_codes(self, unused: torch.Tensor, candidates: torch.Tensor, generator: torch.Generator) -> int:
        """Overwrite unused codes with randomly drawn candidate vectors of the same dimension.

        Args:
            unused: (A, V) bool, True for codes to re-seed.
            candidates: (A, N, C) float residual vectors per dimension (see `residual_vectors`).
            generator: CPU generator making the draw reproducible.

        Returns:
            Number of codes overwritten.
        """
        num_dimensions, codebook_size, _ = self.codebook.shape
        draws = torch.randint(candidates.shape[1], (num_dimensions, codebook_size), generator=generator)
        draws = draws.to(candidates.device)
        replacements = torch.gather(
            candidates, 1, draws.unsqueeze(-1).expand(-1, -1, candidates.shape[-1])
        )  # (A, V, C)
        mask = unused.to(self.codebook.device).unsqueeze(-1)
        self.codebook.copy_(torch.where(mask, replacements.to(self.codebook.dtype), self.codebook))
        return int(unused.sum())
