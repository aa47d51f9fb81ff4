"""DP-T: Diffusion Policy's transformer denoiser (a decoder over action tokens, conditioned through cross-attention).

Follows the paper (Chi et al., "Diffusion Policy", RSS 2023, section III-B) and the official
`diffusion_policy/model/diffusion/transformer_for_diffusion.py` in the configuration DP uses for state observations
(`time_as_cond`, `obs_as_cond`, causal attention, no condition encoder layers):

- Each of the H noisy actions is one token: Linear(A -> D) plus a learned position embedding.
- The condition is 1 + To tokens: the sinusoidal embedding of the diffusion step, then one Linear(Do -> D)
  embedding per observation step, plus a learned position embedding, passed through a two-layer Mish MLP. These are
  the memory of a stack of pre-norm `nn.TransformerDecoderLayer`s (GELU, feed-forward 4 D).
- Masks, as DP builds them: action token t attends to action tokens 0..t (causal self-attention) and to memory
  tokens 0..t + 1, i.e. the step token and observation steps 0..t (memory index s holds observation s - 1).
- A final LayerNorm and Linear(D -> A) give the predicted noise.

Deviation: for inference, :meth:`DiffusionTransformer.prepare` computes the memory once per chunk: the observation
tokens' memory once, the step token's memory for all sampler steps in one batch; a denoising step then only
concatenates its step token to the observation tokens. Same values as DP's per-step computation.
"""

from dataclasses import dataclass

import torch
from torch import nn

from carp.policies.base import check_dimensions, check_observation_shape
from carp.policies.diffusion.config import DiffusionTransformerConfig
from carp.policies.diffusion.embedding import SinusoidalStepEmbedding

INIT_STD = 0.02
"""Normal initialization of linear weights and position embeddings, as DP (and GPT-2) use."""


@dataclass
class TransformerCondition:
    """What a chunk's denoising steps reuse, from :meth:`DiffusionTransformer.prepare`.

    Attributes:
        step_memory: (N, 1, D) encoded step token at each of the N sampler steps.
        observation_memory: (B, To, D) encoded observation tokens.
    """

    step_memory: torch.Tensor
    observation_memory: torch.Tensor


class DiffusionTransformer(nn.Module):
    """Predicts the noise in a noisy action chunk given the diffusion step and the observations.

    Args:
        config: the family's config (num_layers, num_heads, width, dropouts).
        action_dim: `A`, features per action token.
        obs_dim: `Do`, features per observation token.
        obs_steps: `To`, observation tokens.
        action_horizon: `H`, action tokens (the position embedding has one row per token).
    """

    def __init__(
        self, config: DiffusionTransformerConfig, action_dim: int, obs_dim: int, obs_steps: int, action_horizon: int
    ) -> None:
        super().__init__()
        check_dimensions(action_dim=action_dim, obs_dim=obs_dim, obs_steps=obs_steps, action_horizon=action_horizon)
        self.config = config
        self.action_dim = action_dim
        self.obs_dim = obs_dim
        self.obs_steps = obs_steps
        self.action_horizon = action_horizon
        width = config.width

        self.action_embedding = nn.Linear(action_dim, width)
        self.action_position = nn.Parameter(torch.zeros(1, action_horizon, width))
        self.step_embedding = SinusoidalStepEmbedding(width)
        self.observation_embedding = nn.Linear(obs_dim, width)
        self.condition_position = nn.Parameter(torch.zeros(1, 1 + obs_steps, width))
        self.embedding_dropout = nn.Dropout(config.embedding_dropout)
        self.condition_encoder = nn.Sequential(nn.Linear(width, 4 * width), nn.Mish(), nn.Linear(4 * width, width))
        layer = nn.TransformerDecoderLayer(
            d_model=width,
            nhead=config.num_heads,
            dim_feedforward=4 * width,
            dropout=config.attention_dropout,
            activation="gelu",
            batch_first=True,
            norm_first=True,
        )
        self.decoder = nn.TransformerDecoder(layer, num_layers=config.num_layers)
        self.final_norm = nn.LayerNorm(width)
        self.head = nn.Linear(width, action_dim)

        # torch's attention masks are True where attention is NOT allowed.
        action_index = torch.arange(action_horizon)[:, None]
        self.register_buffer(
            "action_mask", torch.arange(action_horizon)[None, :] > action_index, persistent=False
        )  # (H, H)
        self.register_buffer(
            "memory_mask", torch.arange(1 + obs_steps)[None, :] > action_index + 1, persistent=False
        )  # (H, 1 + To)
        self._initialize_weights()

    def _initialize_weights(self) -> None:
        for module in self.modules():
            if isinstance(module, nn.Linear):
                nn.init.normal_(module.weight, std=INIT_STD)
                nn.init.zeros_(module.bias)
            elif isinstance(module, nn.MultiheadAttention):
                nn.init.normal_(module.in_proj_weight, std=INIT_STD)
                nn.init.zeros_(module.in_proj_bias)
        nn.init.normal_(self.action_position, std=INIT_STD)
        nn.init.normal_(self.condition_position, std=INIT_STD)

    def parameter_groups(self, weight_decay: float) -> list[dict]:
        """AdamW groups as DP forms them: weight matrices decay; biases, norms and position embeddings do not."""
        no_decay_names = {"action_position", "condition_position"}
        decay, no_decay = [], []
        for name, parameter in self.named_parameters():
            (decay if parameter.dim() >= 2 and name not in no_decay_names else no_decay).append(parameter)
        return [{"params": decay, "weight_decay": weight_decay}, {"params": no_decay, "weight_decay": 0.0}]

    def _check_inputs(self, obs_features: torch.Tensor, action_horizon: int) -> None:
        check_observation_shape(obs_features, self.obs_steps, self.obs_dim, "obs_features")
        if action_horizon != self.action_horizon:
            raise ValueError(f"this transformer denoises H={self.action_horizon} actions, got H={action_horizon}")

    def _encode_condition(self, condition_tokens: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
        return self.condition_encoder(self.embedding_dropout(condition_tokens + positions))

    def forward(self, noisy_actions: torch.Tensor, steps: torch.Tensor, obs_features: torch.Tensor) -> torch.Tensor:
        """Predict the noise of a batch whose samples may be at different diffusion steps (training).

        Args:
            noisy_actions: (B, H, A) noised normalized actions.
            steps: (B,) long diffusion step of each sample.
            obs_features: (B, To, Do) normalized observations.

        Returns:
            (B, H, A) predicted noise.
        """
        self._check_inputs(obs_features, noisy_actions.shape[1])
        condition_tokens = torch.cat(
            (self.step_embedding(steps).unsqueeze(1), self.observation_embedding(obs_features)), dim=1
        )  # (B, 1 + To, D)
        memory = self._encode_condition(condition_tokens, self.condition_position)  # (B, 1 + To, D)
        return self._denoise(noisy_actions, memory)

    @torch.no_grad()
    def prepare(self, obs_features: torch.Tensor, steps: torch.Tensor, action_horizon: int) -> TransformerCondition:
        """Precompute the memory of one chunk's denoising steps.

        Args:
            obs_features: (B, To, Do) normalized observations.
            steps: (N,) long, the sampler's diffusion steps in calling order.
            action_horizon: `H` of the chunk to sample; must equal the transformer's.

        Returns:
            The encoded step and observation tokens to pass to :meth:`predict_noise` at every step.
        """
        self._check_inputs(obs_features, action_horizon)
        step_tokens = self.step_embedding(steps.to(obs_features.device)).unsqueeze(1)  # (N, 1, D)
        step_memory = self._encode_condition(step_tokens, self.condition_position[:, :1])  # (N, 1, D)
        observation_memory = self._encode_condition(
            self.observation_embedding(obs_features), self.condition_position[:, 1:]
        )  # (B, To, D)
        return TransformerCondition(step_memory, observation_memory)

    def predict_noise(
        self, noisy_actions: torch.Tensor, condition: TransformerCondition, step_index: int
    ) -> torch.Tensor:
        """Predict the noise at the `step_index`-th sampler step (inference).

        Args:
            noisy_actions: (B, H, A) current sample.
            condition: from :meth:`prepare` for these observations and the sampler's steps.
            step_index: position of the current step in the `steps` given to :meth:`prepare`.

        Returns:
            (B, H, A) predicted noise.
        """
        observation_memory = condition.observation_memory
        step_memory = condition.step_memory[step_index].expand(observation_memory.shape[0], -1, -1)  # (B, 1, D)
        memory = torch.cat((step_memory, observation_memory), dim=1)  # (B, 1 + To, D)
        return self._denoise(noisy_actions, memory)

    def _denoise(self, noisy_actions: torch.Tensor, memory: torch.Tensor) -> torch.Tensor:
        tokens = self.embedding_dropout(self.action_embedding(noisy_actions) + self.action_position)  # (B, H, D)
        hidden = self.decoder(tokens, memory, tgt_mask=self.action_mask, memory_mask=self.memory_mask)  # (B, H, D)
        return self.head(self.final_norm(hidden))  # (B, H, A)
