"""DP-C: Diffusion Policy's 1-D temporal convolutional U-Net with FiLM conditioning.

Follows the paper (Chi et al., "Diffusion Policy", RSS 2023, section III-B) and the official
`diffusion_policy/model/diffusion/conditional_unet1d.py` with global observation conditioning: the action chunk
(B, H, A) is a 1-D signal of A channels over H steps; a U-Net of residual blocks (two Conv1d-GroupNorm-Mish blocks
each) denoises it. The condition, [diffusion-step embedding, the `To` observation steps flattened], modulates every
residual block by FiLM: a per-channel scale and bias applied between its two convolutions. Every level but the
coarsest halves the horizon (strided conv) and every up level doubles it (transposed conv), so H must be a multiple
of `2 ** (levels - 1)` (4 with three levels).

Kept from the official network, for the parameter count and behaviour: the finest level's output is not
concatenated back (the up path has one level fewer than the down path, and its first block reads the coarsest
skip); the final Conv1d-GroupNorm-Mish block and 1x1 projection. Deviations:

- Mish is applied once to the shared condition vector rather than inside every block's FiLM encoder (same values).
- For inference, :meth:`ConditionalUNet1D.prepare` splits each FiLM projection into its step part and its
  observation part (the projection is linear and Mish acts element-wise) and computes the step part for every
  sampler step and the observation part once per chunk, so a denoising step adds two precomputed vectors per block
  instead of running the step MLP and one Linear per block.
- No local (per-step) conditioning and no inpainting of observations: global conditioning only, as DP uses it
  for state observations in its robomimic experiments.

With `num_step_inputs` = 2 the condition holds two step embeddings, both from the one step encoder, before the
observations: Consistency Policy's student (`carp.policies.consistency`) reads its current and its target noise
level this way, as the official CTM U-Net does.
"""

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from carp.policies.base import check_dimensions, check_observation_shape
from carp.policies.diffusion.config import UNetSettings
from carp.policies.diffusion.embedding import step_encoder


class ConvNormMish(nn.Sequential):
    """Conv1d (same padding) -> GroupNorm -> Mish; (B, C_in, H) -> (B, C_out, H)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, num_groups: int) -> None:
        super().__init__(
            nn.Conv1d(in_channels, out_channels, kernel_size, padding=kernel_size // 2),
            nn.GroupNorm(num_groups, out_channels),
            nn.Mish(),
        )


class FiLMResidualBlock(nn.Module):
    """Two conv blocks with a FiLM scale and bias between them, plus a residual path.

    Args:
        in_channels: channels of the input.
        out_channels: channels of the output.
        condition_dim: width of the condition vector the FiLM projection reads.
        kernel_size: temporal kernel of both convolutions.
        num_groups: GroupNorm groups.
    """

    def __init__(
        self, in_channels: int, out_channels: int, condition_dim: int, kernel_size: int, num_groups: int
    ) -> None:
        super().__init__()
        self.out_channels = out_channels
        self.first = ConvNormMish(in_channels, out_channels, kernel_size, num_groups)
        self.second = ConvNormMish(out_channels, out_channels, kernel_size, num_groups)
        self.film = nn.Linear(condition_dim, 2 * out_channels)
        self.residual = nn.Conv1d(in_channels, out_channels, 1) if in_channels != out_channels else nn.Identity()

    def forward(self, hidden: torch.Tensor, film: torch.Tensor) -> torch.Tensor:
        """Apply the block.

        Args:
            hidden: (B, C_in, H).
            film: (B, 2 * C_out, 1), scales then biases (this block's FiLM projection of the condition).

        Returns:
            (B, C_out, H).
        """
        scale, bias = film.split(self.out_channels, dim=1)  # (B, C_out, 1) each
        modulated = torch.addcmul(bias, self.first(hidden), scale)  # (B, C_out, H)
        return self.second(modulated) + self.residual(hidden)


class UNetLevel(nn.Module):
    """Two residual blocks at one resolution, then a change of resolution (or none at the coarsest level)."""

    def __init__(self, first: FiLMResidualBlock, second: FiLMResidualBlock, resample: nn.Module) -> None:
        super().__init__()
        self.first = first
        self.second = second
        self.resample = resample


@dataclass
class UNetCondition:
    """What a chunk's denoising steps reuse, from :meth:`ConditionalUNet1D.prepare`.

    Attributes:
        step_films: per residual block, (N, 2 * C, 1): the step part of its FiLM projection at each of the N
            sampler steps.
        observation_films: per residual block, (B, 2 * C, 1): the observation part plus the projection's bias.
        action_horizon: `H` of the chunk being sampled.
    """

    step_films: list[torch.Tensor]
    observation_films: list[torch.Tensor]
    action_horizon: int


class ConditionalUNet1D(nn.Module):
    """Predicts the noise in a noisy action chunk given the diffusion step and the observations.

    Args:
        config: the family's config (down_dims, kernel_size, num_groups, step_embedding_dim).
        action_dim: `A`, channels of the denoised signal.
        obs_dim: `Do`, observation features per step.
        obs_steps: `To`, observation steps conditioned on.
        num_step_inputs: steps (noise levels) each sample is conditioned on, `k`: 1 for a denoiser, 2 for a
            consistency-trajectory student (its current and target levels).
    """

    def __init__(
        self, config: UNetSettings, action_dim: int, obs_dim: int, obs_steps: int, num_step_inputs: int = 1
    ) -> None:
        super().__init__()
        check_dimensions(action_dim=action_dim, obs_dim=obs_dim, obs_steps=obs_steps, num_step_inputs=num_step_inputs)
        self.config = config
        self.action_dim = action_dim
        self.obs_dim = obs_dim
        self.obs_steps = obs_steps
        self.num_step_inputs = num_step_inputs
        step_dim = config.step_embedding_dim
        condition_dim = num_step_inputs * step_dim + obs_steps * obs_dim
        kernel, groups = config.kernel_size, config.num_groups

        def residual_block(in_channels: int, out_channels: int) -> FiLMResidualBlock:
            return FiLMResidualBlock(in_channels, out_channels, condition_dim, kernel, groups)

        self.step_encoder = step_encoder(step_dim)
        channels = (action_dim, *config.down_dims)
        num_levels = len(config.down_dims)
        self.down_levels = nn.ModuleList(
            UNetLevel(
                residual_block(channels[index], channels[index + 1]),
                residual_block(channels[index + 1], channels[index + 1]),
                nn.Conv1d(channels[index + 1], channels[index + 1], 3, stride=2, padding=1)
                if index + 1 < num_levels
                else nn.Identity(),
            )
            for index in range(num_levels)
        )
        coarsest = config.down_dims[-1]
        self.middle = nn.ModuleList((residual_block(coarsest, coarsest), residual_block(coarsest, coarsest)))
        # Up level for down level `index` (coarsest first, the finest excluded): reads its skip beside the hidden
        # state, hence twice its channels, and returns to the next finer level's channels at twice the length.
        self.up_levels = nn.ModuleList(
            UNetLevel(
                residual_block(2 * config.down_dims[index], config.down_dims[index - 1]),
                residual_block(config.down_dims[index - 1], config.down_dims[index - 1]),
                nn.ConvTranspose1d(config.down_dims[index - 1], config.down_dims[index - 1], 4, stride=2, padding=1),
            )
            for index in reversed(range(1, num_levels))
        )
        finest = config.down_dims[0]
        self.final = nn.Sequential(ConvNormMish(finest, finest, kernel, groups), nn.Conv1d(finest, action_dim, 1))
        # Residual blocks in the order the forward pass consumes their FiLM vectors (a tuple, not a registered
        # container, so the parameters are not listed twice in the state dict).
        self._film_blocks: tuple[FiLMResidualBlock, ...] = tuple(
            block
            for level_blocks in (
                *((level.first, level.second) for level in self.down_levels),
                tuple(self.middle),
                *((level.first, level.second) for level in self.up_levels),
            )
            for block in level_blocks
        )

    def _check_inputs(self, obs_features: torch.Tensor, action_horizon: int) -> None:
        check_observation_shape(obs_features, self.obs_steps, self.obs_dim, "obs_features")
        multiple = self.config.horizon_multiple
        if action_horizon < 1 or action_horizon % multiple:
            raise ValueError(
                f"action horizon H={action_horizon} must be a positive multiple of {multiple} "
                f"(2 ** (levels - 1) with {len(self.config.down_dims)} levels)"
            )

    def _step_features(self, steps: torch.Tensor) -> torch.Tensor:
        """(N, k * step_dim) embeddings of steps (N,) (k = 1) or (N, k), each column embedded by the one encoder."""
        columns = steps.reshape(steps.shape[0], -1)  # (N, k)
        if columns.shape[1] != self.num_step_inputs:
            raise ValueError(
                f"steps must have shape (N,) or (N, {self.num_step_inputs}) for {self.num_step_inputs} step inputs, "
                f"got {tuple(steps.shape)}"
            )
        return self.step_encoder(columns.flatten()).reshape(columns.shape[0], -1)  # (N, k * step_dim)

    def forward(self, noisy_actions: torch.Tensor, steps: torch.Tensor, obs_features: torch.Tensor) -> torch.Tensor:
        """Predict the noise of a batch whose samples may be at different diffusion steps (training).

        Args:
            noisy_actions: (B, H, A) noised normalized actions.
            steps: (B,) diffusion step of each sample (long, or float noise-level inputs), or (B, k) with
                `num_step_inputs` = k.
            obs_features: (B, To, Do) normalized observations.

        Returns:
            (B, H, A) predicted noise (or whatever output the network is trained for).
        """
        self._check_inputs(obs_features, noisy_actions.shape[1])
        condition = torch.cat(
            (self._step_features(steps), obs_features.flatten(1)), dim=1
        )  # (B, k * step_dim + To * Do)
        condition = F.mish(condition)
        films = [block.film(condition).unsqueeze(-1) for block in self._film_blocks]  # (B, 2 * C, 1) each
        return self._denoise(noisy_actions, films)

    @torch.no_grad()
    def prepare(self, obs_features: torch.Tensor, steps: torch.Tensor, action_horizon: int) -> UNetCondition:
        """Precompute the conditioning of one chunk's denoising steps.

        Args:
            obs_features: (B, To, Do) normalized observations.
            steps: (N,) or (N, k), the sampler's diffusion steps in calling order.
            action_horizon: `H` of the chunk to sample.

        Returns:
            The FiLM parts to pass to :meth:`predict_noise` at every step.
        """
        self._check_inputs(obs_features, action_horizon)
        step_dim = self.num_step_inputs * self.config.step_embedding_dim
        step_features = F.mish(self._step_features(steps.to(obs_features.device)))  # (N, k * step_dim)
        obs_flat = F.mish(obs_features.flatten(1))  # (B, To * Do)
        step_films, observation_films = [], []
        for block in self._film_blocks:
            weight = block.film.weight  # (2 * C, k * step_dim + To * Do)
            step_films.append(F.linear(step_features, weight[:, :step_dim]).unsqueeze(-1))  # (N, 2 * C, 1)
            observation_films.append(
                F.linear(obs_flat, weight[:, step_dim:], block.film.bias).unsqueeze(-1)
            )  # (B, 2 * C, 1)
        return UNetCondition(step_films, observation_films, action_horizon)

    def predict_noise(self, noisy_actions: torch.Tensor, condition: UNetCondition, step_index: int) -> torch.Tensor:
        """Predict the noise at the `step_index`-th sampler step (inference).

        Args:
            noisy_actions: (B, H, A) current sample.
            condition: from :meth:`prepare` for these observations and the sampler's steps.
            step_index: position of the current step in the `steps` given to :meth:`prepare`.

        Returns:
            (B, H, A) predicted noise.
        """
        films = [
            observation + step[step_index]
            for step, observation in zip(condition.step_films, condition.observation_films)
        ]  # (B, 2 * C, 1) each
        return self._denoise(noisy_actions, films)

    def _denoise(self, noisy_actions: torch.Tensor, films: list[torch.Tensor]) -> torch.Tensor:
        film = iter(films)
        hidden = noisy_actions.transpose(1, 2)  # (B, A, H)
        skips = []
        for level in self.down_levels:
            hidden = level.second(level.first(hidden, next(film)), next(film))  # (B, C_l, H_l)
            skips.append(hidden)
            hidden = level.resample(hidden)  # (B, C_l, H_{l+1})
        for block in self.middle:
            hidden = block(hidden, next(film))
        for level in self.up_levels:
            hidden = torch.cat((hidden, skips.pop()), dim=1)  # (B, 2 * C_l, H_l)
            hidden = level.second(level.first(hidden, next(film)), next(film))  # (B, C_{l-1}, H_l)
            hidden = level.resample(hidden)  # (B, C_{l-1}, H_{l-1})
        return self.final(hidden).transpose(1, 2)  # (B, H, A)
