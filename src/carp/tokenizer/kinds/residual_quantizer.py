"""Residual vector quantizer with EMA codebook updates: VQ-BeT's discretization of an action chunk's latent.

Each layer quantizes what the layers before it left over (residual VQ, as in SoundStream), so a latent is described
coarse to fine by one code per layer. Codebooks are not trained by gradients: each code moves towards the mean of the
latents assigned to it with an exponential moving average (van den Oord et al. 2017, appendix; the EMA variant of
the `vector-quantize-pytorch` package that VQ-BeT uses). The commitment loss is that package's, summed over layers:
each layer pulls the residual it receives towards its chosen code. The first layer's term ties the latent itself to
the coarsest codes; a loss on the sum of the codes alone leaves the latent's scale free, and it then grows without
bound while the first layer's codes collapse to one or two. Deviations from VQ-BeT's setup:

- Codebooks start from latents of the first training batch (each layer from its own residuals, drawn with the
  caller's generator) instead of a k-means initialization: deterministic given the seed and cheap.
- No dead-code replacement and no codebook orthogonality loss (both off in VQ-BeT's configs).
"""

import torch
import torch.nn.functional as F
from torch import nn

EMA_EPSILON = 1e-5
"""Laplace smoothing of the EMA cluster sizes, so that an unused code never divides by zero."""


class ResidualVectorQuantizer(nn.Module):
    """`num_layers` codebooks of `num_codes` vectors each; a latent becomes one code per layer.

    Args:
        num_layers: residual layers (VQ-BeT: 2, a primary and a secondary code).
        num_codes: codes per layer (VQ-BeT: 16).
        latent_width: width of the latents and codes.
        decay: EMA decay of the codebook statistics per update, in (0, 1).
    """

    def __init__(self, num_layers: int, num_codes: int, latent_width: int, decay: float) -> None:
        super().__init__()
        if num_layers < 1 or num_codes < 2 or latent_width < 1:
            raise ValueError(
                f"need num_layers >= 1, num_codes >= 2, latent_width >= 1; got {num_layers}, {num_codes}, "
                f"{latent_width}"
            )
        if not 0.0 < decay < 1.0:
            raise ValueError(f"decay must be in (0, 1), got {decay}")
        self.num_layers = num_layers
        self.num_codes = num_codes
        self.latent_width = latent_width
        self.decay = decay
        # Buffers, not parameters: the codebooks follow the EMA, never the optimizer.
        self.register_buffer("codebooks", torch.zeros(num_layers, num_codes, latent_width))
        self.register_buffer("cluster_sizes", torch.zeros(num_layers, num_codes))
        self.register_buffer("code_sums", torch.zeros(num_layers, num_codes, latent_width))
        self.register_buffer("initialized", torch.tensor(False))

    @torch.no_grad()
    def initialize(self, latent: torch.Tensor, generator: torch.Generator | None = None) -> None:
        """Set each layer's codebook to `num_codes` residuals of `latent`, drawn without replacement.

        Args:
            latent: (N, latent_width) latents, N >= num_codes (with repeats when fewer).
            generator: random source of the draws (seeded for a reproducible codebook).
        """
        residual = latent.detach().float()
        for layer in range(self.num_layers):
            count = residual.shape[0]
            if count >= self.num_codes:
                rows = torch.randperm(count, generator=generator, device="cpu")[: self.num_codes]
            else:
                rows = torch.randint(count, (self.num_codes,), generator=generator, device="cpu")
            self.codebooks[layer] = residual[rows.to(residual.device)]
            self.code_sums[layer] = self.codebooks[layer]
            self.cluster_sizes[layer] = 1.0
            residual = residual - self.codebooks[layer][self._nearest(residual, layer)]
        self.initialized.fill_(True)

    def _nearest(self, residual: torch.Tensor, layer: int) -> torch.Tensor:
        """(N,) long index of the code of `layer` closest (Euclidean) to each of the (N, latent_width) residuals."""
        return torch.cdist(residual, self.codebooks[layer]).argmin(dim=-1)

    def encode_to_ids(self, latent: torch.Tensor) -> torch.Tensor:
        """(N, latent_width) latents -> (N, num_layers) long code ids, layer by layer on the residual."""
        residual = latent.float()
        ids = []
        for layer in range(self.num_layers):
            layer_ids = self._nearest(residual, layer)  # (N,)
            residual = residual - self.codebooks[layer][layer_ids]
            ids.append(layer_ids)
        return torch.stack(ids, dim=1)  # (N, num_layers)

    def ids_to_latent(self, code_ids: torch.Tensor) -> torch.Tensor:
        """(N, num_layers) long code ids -> (N, latent_width) quantized latents: the sum of the chosen codes."""
        layers = torch.arange(self.num_layers, device=code_ids.device)
        return self.codebooks[layers, code_ids].sum(dim=1)  # (N, latent_width)

    def forward(self, latent: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Quantize, update the codebooks by EMA when training, and pass gradients straight through.

        Args:
            latent: (N, latent_width) encoder output.

        Returns:
            The quantized latent (N, latent_width) with straight-through gradients to `latent`, the code ids
            (N, num_layers) long, and the commitment loss (scalar): over the layers, the sum of the mean squared
            distance between the residual a layer receives (a function of `latent`) and its detached code, which
            pulls the encoder towards the codebooks.

        Raises:
            RuntimeError: the codebooks were never initialized.
        """
        if not bool(self.initialized):
            raise RuntimeError("the codebooks are not initialized; call initialize() with training latents first")
        residual = latent.float()  # keeps the graph to `latent`: each layer's commitment term reaches the encoder
        ids = []
        commitment = latent.new_zeros(())
        for layer in range(self.num_layers):
            layer_ids = self._nearest(residual.detach(), layer)  # (N,)
            if self.training:
                self._update_codebook(layer, residual.detach(), layer_ids)
            code = self.codebooks[layer][layer_ids]  # (N, latent_width), a buffer: no gradient
            commitment = commitment + F.mse_loss(residual, code)
            residual = residual - code
            ids.append(layer_ids)
        code_ids = torch.stack(ids, dim=1)  # (N, num_layers)
        quantized = self.ids_to_latent(code_ids).to(latent.dtype)
        return latent + (quantized - latent).detach(), code_ids, commitment

    @torch.no_grad()
    def _update_codebook(self, layer: int, residual: torch.Tensor, layer_ids: torch.Tensor) -> None:
        """One EMA step of `layer`'s counts and sums towards this batch's assignments, then the codebook itself."""
        one_hot = F.one_hot(layer_ids, self.num_codes).to(residual.dtype)  # (N, num_codes)
        self.cluster_sizes[layer].lerp_(one_hot.sum(dim=0), 1.0 - self.decay)
        self.code_sums[layer].lerp_(one_hot.T @ residual, 1.0 - self.decay)
        sizes = self.cluster_sizes[layer]
        total = sizes.sum()
        smoothed = (sizes + EMA_EPSILON) / (total + self.num_codes * EMA_EPSILON) * total
        self.codebooks[layer] = self.code_sums[layer] / smoothed.unsqueeze(1)
