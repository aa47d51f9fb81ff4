"""Exponential moving average of a denoiser's weights with Diffusion Policy's warmup, on torch's `AveragedModel`.

DP (`diffusion_policy/model/diffusion/ema_model.py`, `inv_gamma` 1, `power` 0.75, `max_value` 0.9999) lets the decay
grow with the number of updates, so the average follows the fast-changing early weights and then settles:
after n averaged updates the next one uses `decay = min(max_decay, 1 - n ** -power)` (0, a plain copy, for n = 1).
torch's `AveragedModel` counts the updates and keeps the averaged copy; its `get_ema_multi_avg_fn` applies one
decay to all parameters at once. The first update copies the weights (AveragedModel's rule), which with the second
(decay 0) matches DP's first two updates.
"""

import torch
from torch import nn
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn


def warmup_decay(num_averaged: int, power: float, max_decay: float) -> float:
    """EMA decay of the update after `num_averaged` >= 1 updates: `min(max_decay, 1 - num_averaged ** -power)`."""
    return min(max_decay, max(0.0, 1.0 - num_averaged**-power))


def exponential_moving_average(model: nn.Module, power: float = 0.75, max_decay: float = 0.9999) -> AveragedModel:
    """A copy of `model` whose weights track their exponential moving average with DP's warmup.

    Call `.update_parameters(model)` after every optimizer step; evaluate `.module`. Buffers are copied, not averaged
    (the denoisers' buffers are constants: frequencies and masks).

    Args:
        model: the network being trained.
        power: warmup exponent, in (0, 1].
        max_decay: cap of the decay, in [0, 1).

    Returns:
        The averaged model (its `n_averaged` buffer counts the updates).
    """

    # The count comes from AveragedModel's `n_averaged` buffer, which its state dict saves, so an average restored
    # from a checkpoint resumes its warmup where it stopped.
    def average(averaged: list[torch.Tensor], current: list[torch.Tensor], num_averaged: torch.Tensor) -> None:
        get_ema_multi_avg_fn(warmup_decay(int(num_averaged), power, max_decay))(averaged, current, num_averaged)

    return AveragedModel(model, multi_avg_fn=average, use_buffers=False)
