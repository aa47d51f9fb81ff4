"""Mean cross entropy of low-precision logits, computed in float32 one block of rows at a time.

`F.cross_entropy` on bfloat16 logits first needs a float32 copy of the whole (M, V) tensor, keeps its log-softmax
for the backward pass and builds the gradient in float32 before it is cast back: several passes over the largest
tensor of a training step (batch x L rows of V logits). Here each block of rows is converted, reduced and discarded
while it is still in cache; the backward pass recomputes the block's softmax from the saved log-sum-exp and writes
the gradient straight in the logits' dtype. The arithmetic is float32 throughout, so the loss equals
`F.cross_entropy(logits.float(), targets)` up to summation order. Under bfloat16 autocast on the CPU, fewer passes
over that tensor make a training step faster than `F.cross_entropy` on a float32 copy, which is why the policies
take their loss (and their accuracy's argmax) through this function.
"""

import torch

DEFAULT_BLOCK_ROWS = 1024
"""Rows per block: 1,024 x 512 float32 logits are 2 MiB."""


class _BlockwiseCrossEntropy(torch.autograd.Function):
    @staticmethod
    def forward(ctx, logits: torch.Tensor, targets: torch.Tensor, block_rows: int) -> torch.Tensor:
        log_sum_exp = torch.empty(logits.shape[0], dtype=torch.float32, device=logits.device)  # (M,)
        for start in range(0, logits.shape[0], block_rows):
            block = logits[start : start + block_rows].float()  # (m, V)
            log_sum_exp[start : start + block_rows] = torch.logsumexp(block, dim=-1)
        target_logits = logits.gather(1, targets.unsqueeze(1)).squeeze(1).float()  # (M,)
        ctx.save_for_backward(logits, targets, log_sum_exp)
        ctx.block_rows = block_rows
        return (log_sum_exp - target_logits).mean()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_loss: torch.Tensor) -> tuple[torch.Tensor, None, None]:
        logits, targets, log_sum_exp = ctx.saved_tensors
        rows = logits.shape[0]
        grad_logits = torch.empty_like(logits)  # (M, V)
        block_rows = ctx.block_rows
        for start in range(0, rows, block_rows):
            end = min(start + block_rows, rows)
            # d(mean loss)/d(logit) = (softmax - one_hot(target)) / M
            probabilities = torch.exp(logits[start:end].float() - log_sum_exp[start:end, None])  # (m, V)
            probabilities[torch.arange(end - start, device=logits.device), targets[start:end]] -= 1.0
            grad_logits[start:end] = probabilities.mul_(grad_loss / rows)
        return grad_logits, None, None


def blockwise_cross_entropy(
    logits: torch.Tensor, targets: torch.Tensor, block_rows: int = DEFAULT_BLOCK_ROWS
) -> torch.Tensor:
    """Mean cross entropy, as `F.cross_entropy(logits.float(), targets)`, without a float32 copy of `logits`.

    Args:
        logits: (M, V) float32, bfloat16 or float16.
        targets: (M,) long class ids in [0, V).
        block_rows: rows converted to float32 at a time.

    Returns:
        Scalar float32 loss; its gradient flows to `logits` in their own dtype.
    """
    if logits.dim() != 2 or targets.shape != logits.shape[:1]:
        shapes = f"{tuple(logits.shape)} and {tuple(targets.shape)}"
        raise ValueError(f"blockwise_cross_entropy expects logits (M, V) and targets (M,), got {shapes}")
    return _BlockwiseCrossEntropy.apply(logits, targets, block_rows)
