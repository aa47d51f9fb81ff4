"""Focal loss (Lin et al. 2017), which VQ-BeT puts on its code predictions.

Cross entropy scaled by `(1 - p_t) ** gamma`, with `p_t` the predicted probability of the target class: well
classified samples weigh less, so the rare codes of a skewed code distribution are not drowned. `gamma = 0` is cross
entropy. No class weights (alpha), as in VQ-BeT.
"""

import torch
import torch.nn.functional as F


def focal_loss(logits: torch.Tensor, targets: torch.Tensor, gamma: float) -> torch.Tensor:
    """Mean focal loss of a batch.

    Args:
        logits: (N, C) unnormalized class scores (computed in float32 whatever their dtype).
        targets: (N,) long target classes in [0, C).
        gamma: focusing exponent, >= 0.

    Returns:
        Scalar float32 loss.
    """
    if gamma < 0:
        raise ValueError(f"gamma must be >= 0, got {gamma}")
    log_probabilities = F.log_softmax(logits.float(), dim=-1)
    target_log_probability = log_probabilities.gather(1, targets.unsqueeze(1)).squeeze(1)  # (N,)
    weight = (1.0 - target_log_probability.exp()).pow(gamma)
    return -(weight * target_log_probability).mean()
