"""VQ-BeT's GPT over the observation window, with its code head and offset head.

Source: Lee et al., "Behavior Generation with Latent Actions" (ICML 2024) and its public code: a nanoGPT-style
decoder (pre-LayerNorm blocks with biases, causal self-attention, GELU MLP of 4x width, learned position embedding,
an output projection without bias), then two MLPs with two 1024-wide hidden layers on its output: one scores the
codes of every residual layer (`num_residual_layers x num_codes` logits), the other predicts a continuous offset of
the whole chunk for every (layer, code) pair. The offset of a chunk is the sum over layers of the offsets of its
chosen codes, added to the VQ-VAE's decoding of those codes.

Deviations: the attention and MLP modules are carp's (`carp.policies.carp.blocks`: a fused qkv projection and exact
GELU); only the last observation step's output is read, and it predicts the pipeline's whole chunk of H actions
starting at the first observation step (carp's window convention), where VQ-BeT predicts a chunk at every step of
its window.

Size at the defaults, Push-T's state (Do = 20, A = 2) and carp's protocol (To = 2, H = 16): 4,787,816 trained
parameters (GPT 1,079,880, code head 1,345,568, offset head 2,362,368); the offset head's last layer grows with
H * A (32,800 parameters per action value).
"""

import torch
from einops import rearrange
from torch import nn

from carp.policies.base import check_dimensions
from carp.policies.carp.blocks import FeedForward, SelfAttention
from carp.policies.vq_bet.config import VqBetConfig
from carp.policies.vq_bet.losses import focal_loss
from carp.tokenizer.kinds.chunk_vqvae import multilayer_perceptron

INITIAL_STD = 0.02
"""Standard deviation of the GPT's initial weights (nanoGPT's, which VQ-BeT's GPT inherits)."""


class GptBlock(nn.Module):
    """Pre-LayerNorm decoder block: causal self-attention then MLP, each a residual branch with dropout."""

    def __init__(self, width: int, num_heads: int, dropout: float, layer_index: int) -> None:
        super().__init__()
        self.attention_norm = nn.LayerNorm(width)
        self.attention = SelfAttention(width, num_heads, dropout, layer_index)
        self.feed_forward_norm = nn.LayerNorm(width)
        self.feed_forward = FeedForward(width, 4 * width)
        self.dropout = nn.Dropout(dropout)

    def forward(self, hidden: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """(B, To, D) tokens and the (To, To) bool causal mask -> (B, To, D)."""
        hidden = hidden + self.dropout(self.attention(self.attention_norm(hidden), mask))
        return hidden + self.dropout(self.feed_forward(self.feed_forward_norm(hidden)))


class BehaviorTransformer(nn.Module):
    """GPT over `To` observation features, then code logits and per-code offsets of one action chunk.

    Args:
        config: the family's config (GPT and head sizes, VQ-VAE codes and layers).
        obs_dim: `F`, observation features per step.
        obs_steps: `To`.
        action_horizon: `H`, actions per chunk.
        action_dim: `A`.
    """

    def __init__(self, config: VqBetConfig, obs_dim: int, obs_steps: int, action_horizon: int, action_dim: int) -> None:
        super().__init__()
        check_dimensions(obs_dim=obs_dim, obs_steps=obs_steps, action_horizon=action_horizon, action_dim=action_dim)
        self.config = config
        self.obs_dim = obs_dim
        self.obs_steps = obs_steps
        self.action_horizon = action_horizon
        self.action_dim = action_dim
        width = config.width
        self.input_projection = nn.Linear(obs_dim, width)
        self.position_embedding = nn.Parameter(torch.zeros(1, obs_steps, width))
        self.embedding_dropout = nn.Dropout(config.dropout)
        self.blocks = nn.ModuleList(
            GptBlock(width, config.num_heads, config.dropout, index) for index in range(config.depth)
        )
        self.final_norm = nn.LayerNorm(width)
        self.output_projection = nn.Linear(width, config.output_width, bias=False)
        codes = config.num_residual_layers * config.num_codes
        self.code_head = multilayer_perceptron(config.output_width, config.head_hidden_width, codes)
        self.offset_head = multilayer_perceptron(
            config.output_width, config.head_hidden_width, codes * action_horizon * action_dim
        )
        self.register_buffer("causal_mask", torch.ones(obs_steps, obs_steps, dtype=torch.bool).tril(), persistent=False)
        self._initialize_gpt()

    def _initialize_gpt(self) -> None:
        """Initialize the GPT part as nanoGPT does; the heads keep PyTorch's default, as in VQ-BeT."""
        gpt = [self.input_projection, self.blocks, self.final_norm, self.output_projection]
        for module in (inner for part in gpt for inner in part.modules()):
            if isinstance(module, nn.Linear):
                nn.init.normal_(module.weight, std=INITIAL_STD)
                if module.bias is not None:
                    nn.init.zeros_(module.bias)
        nn.init.normal_(self.position_embedding, std=INITIAL_STD)

    def gpt_modules(self) -> list[nn.Module]:
        """The modules the freeze schedule stops: the GPT and the code head (the offset head keeps training)."""
        return [self.input_projection, self.blocks, self.final_norm, self.output_projection, self.code_head]

    def features(self, obs_features: torch.Tensor) -> torch.Tensor:
        """(B, To, F) normalized observation features -> (B, output_width), the GPT's output at the last step."""
        if obs_features.dim() != 3 or tuple(obs_features.shape[1:]) != (self.obs_steps, self.obs_dim):
            raise ValueError(
                f"obs_features must have shape (B, To, F) = (B, {self.obs_steps}, {self.obs_dim}), got "
                f"{tuple(obs_features.shape)}"
            )
        hidden = self.embedding_dropout(self.input_projection(obs_features) + self.position_embedding)  # (B, To, D)
        for block in self.blocks:
            hidden = block(hidden, self.causal_mask)
        return self.output_projection(self.final_norm(hidden[:, -1]))  # (B, output_width)

    def code_logits(self, features: torch.Tensor) -> torch.Tensor:
        """(B, output_width) -> (B, num_residual_layers, num_codes) logits of each layer's code."""
        return rearrange(self.code_head(features), "b (layer code) -> b layer code", code=self.config.num_codes)

    def code_offsets(self, features: torch.Tensor, code_ids: torch.Tensor) -> torch.Tensor:
        """The chunk offset of the chosen codes: the sum over layers of each chosen code's predicted offset.

        Args:
            features: (B, output_width) GPT output.
            code_ids: (B, num_residual_layers) long chosen codes.

        Returns:
            (B, H, A) normalized offsets.
        """
        config = self.config
        offsets = rearrange(
            self.offset_head(features),
            "b (layer code h a) -> b layer code h a",
            layer=config.num_residual_layers,
            code=config.num_codes,
            h=self.action_horizon,
        )
        layers = torch.arange(config.num_residual_layers, device=code_ids.device)
        batch = torch.arange(code_ids.shape[0], device=code_ids.device).unsqueeze(1)
        return offsets[batch, layers, code_ids].sum(dim=1)  # (B, H, A)


def code_losses(logits: torch.Tensor, code_ids: torch.Tensor, gamma: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Focal losses of the primary code and (the mean over layers) of the secondary codes; the latter 0 if none.

    Args:
        logits: (B, num_residual_layers, num_codes).
        code_ids: (B, num_residual_layers) long target codes.
        gamma: focal exponent.
    """
    primary = focal_loss(logits[:, 0], code_ids[:, 0], gamma)
    if logits.shape[1] == 1:
        return primary, torch.zeros_like(primary)
    secondary = focal_loss(logits[:, 1:].flatten(0, 1), code_ids[:, 1:].flatten(), gamma)
    return primary, secondary
