"""CARP's part of the shared training loop (`carp.training.loop`): token targets, the training step, the recipe.

Recipe (docs/architecture.md, "Teacher-forced training"; after VAR and the official CARP trainer): teacher forcing
with ground-truth tokens, cross entropy over all L tokens, AdamW (betas 0.9/0.95 as in VAR, no weight decay on biases
and embeddings), linear warm-up then cosine decay per step, optional EMA of the weights.

Because the tokenizer is frozen, the ground-truth token ids and the teacher-forcing inputs of every window never change;
they are computed once before training (the loop's `prepare_data`) instead of re-encoding every batch as the official
trainer does.

Learning rate: VAR's rule, 1e-4 x batch / 256, is sized for the paper's 4,000 epochs on a GPU; the CPU budget here is
tens of epochs, so the default peak is 1e-3 with 100 warm-up steps and cosine decay to 1% of the peak. The AdaLN gates
start near zero, which keeps the first steps stable at such rates; the default stays below the largest stable rate as
a margin for long runs over few demonstrations. The rate is a parameter, worth raising when the epoch budget is small.
"""

from __future__ import annotations

import dataclasses
import logging
from copy import deepcopy
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import nn
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from carp.policies.carp.attention import (
    ATTENTION_KERNELS,
    MEASURE_REPEATS,
    faster_kernel,
    time_interleaved,
)
from carp.policies.carp.config import ATTENTION_SETTINGS, CarpConfig
from carp.policies.carp.layout import TokenLayout
from carp.policies.carp.transformer import CoarseToFineTransformer
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer
from carp.training import distributed
from carp.training.checkpoint import CheckpointError, read_training_state
from carp.training.cross_entropy import blockwise_cross_entropy
from carp.training.loop import (
    CHECKPOINT_NAME,
    OptimizerRecipe,
    PolicyTrainingData,
    TrainingStep,
    matrix_decay_groups,
)
from carp.training.runtime import autocast_to, resolve_device, resolve_precision

if TYPE_CHECKING:
    from carp.policies.carp.policy import CarpPolicy
    from carp.policies.registry import TrainingRun

logger = logging.getLogger(__name__)

TOKENIZE_BATCH_SIZE = 4096
ADAM_BETAS = (0.9, 0.95)
ATTENTION_IDENTITY_KEY = "training_attention"
"""The attention kernel a run trains with, in its identity (resumable state) and in the checkpoint's metadata."""


@dataclasses.dataclass
class TokenTargets:
    """Tokenizer outputs of every training window, computed once.

    Attributes:
        token_sequence: (N, L) long ground-truth ids in sequence order.
        teacher_inputs: (N, L - s_1 * A, C) float teacher-forcing inputs of scales 2..K.
    """

    token_sequence: torch.Tensor
    teacher_inputs: torch.Tensor


@torch.no_grad()
def compute_token_targets(tokenizer: MultiScaleActionTokenizer, actions: torch.Tensor) -> TokenTargets:
    """Tokenize (N, H, A) normalized action windows with the frozen tokenizer, in batches, in float32."""
    tokenizer.eval()
    sequences, inputs = [], []
    # The ids must not depend on a surrounding autocast (a training step may run under one).
    with torch.autocast(actions.device.type, enabled=False):
        for batch in torch.split(actions.float(), TOKENIZE_BATCH_SIZE):
            token_ids = tokenizer.encode_to_ids(batch)  # K x (b, A, s_k)
            sequences.append(tokenizer.ids_to_sequence(token_ids))  # (b, L)
            inputs.append(tokenizer.teacher_forcing_sequence(token_ids))  # (b, L - s_1 * A, C)
    return TokenTargets(torch.cat(sequences), torch.cat(inputs))


def teacher_forced_step(transformer: CoarseToFineTransformer, batch: dict[str, torch.Tensor]) -> TrainingStep:
    """Mean cross entropy over all tokens of a teacher-forced forward pass, and the token accuracies' sums.

    Args:
        transformer: the model being trained.
        batch: `obs` (b, To, F) observation features (`CarpPolicy.batch_features`), `teacher_inputs`
            (b, L - s_1 * A, C) and `token_sequence` (b, L) long ground-truth ids.

    Returns:
        The scalar float32 loss, and as metric sums over the batch's windows the fraction of each window's tokens
        whose highest logit is the ground truth: `token_accuracy` over all L tokens and `token_accuracy_scale_<k>`
        over the tokens of scale k = 1..K.
    """
    token_sequence = batch["token_sequence"]
    grouped_logits = transformer(batch["obs"], batch["teacher_inputs"], grouped_by_dimension=True)  # (A, b * L / A, V)
    head = transformer.head
    grouped_targets = head.group(token_sequence)  # (A, b * L / A)
    # Loss in float32 whatever the forward precision; the logits stay in the head's layout and dtype.
    loss = blockwise_cross_entropy(grouped_logits.flatten(0, 1), grouped_targets.flatten())
    # `max(...).indices` rather than `argmax`: same first-maximum ids, and faster on these bfloat16 logits on CPU.
    predicted = head.ungroup(grouped_logits.detach().max(dim=-1).indices, token_sequence.shape[0])  # (b, L)
    correct = (predicted == token_sequence).sum(dim=0, dtype=torch.float64)  # (L,) windows right per position
    spec = transformer.spec
    sums = {"token_accuracy": correct.sum() / spec.sequence_length}
    for scale_index, (start, end) in enumerate(TokenLayout(spec.action_dim, spec.scales).scale_bounds):
        sums[f"token_accuracy_scale_{scale_index + 1}"] = correct[start:end].sum() / (end - start)
    return TrainingStep(loss, sums)


def with_token_targets(policy: CarpPolicy, data: PolicyTrainingData) -> PolicyTrainingData:
    """`data` with its token targets as extras `token_sequence` and `teacher_inputs`, once checked against `policy`.

    Raises:
        ValueError: windows of another shape than the policy's.
    """
    spec = policy.spec
    count = data.obs.shape[0]
    obs_dim = policy.obs_normalizer.num_features
    if data.obs.dim() != 3 or tuple(data.obs.shape[1:]) != (spec.obs_steps, obs_dim):
        raise ValueError(
            f"obs must have shape (N, To, Do) = (N, {spec.obs_steps}, {obs_dim}), got {tuple(data.obs.shape)}"
        )
    expected_actions = (count, policy.tokenizer.spec.action_horizon, spec.action_dim)
    if tuple(data.actions.shape) != expected_actions:
        raise ValueError(f"actions must have shape (N, H, A) = {expected_actions}, got {tuple(data.actions.shape)}")
    targets = compute_token_targets(policy.tokenizer, data.actions)
    extras = {"token_sequence": targets.token_sequence, "teacher_inputs": targets.teacher_inputs}
    return dataclasses.replace(data, extras=data.extras | extras)


def optimizer_recipe(transformer: CoarseToFineTransformer, config: CarpConfig) -> OptimizerRecipe:
    """CARP's AdamW over `transformer`'s parameters, its schedule, and the EMA of the policy's weights."""

    def average(module: nn.Module) -> AveragedModel:
        # Parameters only: the buffers are constant index tables, which averaging would corrupt. The frozen
        # tokenizer's parameters are averaged too, but never change, so their average is exactly themselves.
        return AveragedModel(module, multi_avg_fn=get_ema_multi_avg_fn(config.ema_decay), use_buffers=False)

    return OptimizerRecipe(
        learning_rate=config.learning_rate,
        weight_decay=config.weight_decay,
        warmup_steps=config.warmup_steps,
        betas=ADAM_BETAS,
        ema=average if config.use_ema else None,
        parameter_groups=lambda: matrix_decay_groups(transformer, config.weight_decay),
    )


def measure_attention_kernels(
    transformer: CoarseToFineTransformer,
    batch_size: int,
    device: torch.device,
    precision: torch.dtype,
    repeats: int = MEASURE_REPEATS,
) -> dict[str, float]:
    """Median seconds of a training step's forward and backward pass with each attention kernel, taken in turn.

    The step runs on a copy of `transformer` on `device` under the training precision, with random inputs of the
    training shapes (speed does not depend on the values); the optimizer step is left out, since it does not depend
    on the kernel. Random draws inside (dropout) do not advance the run's generators.

    Returns:
        Kernel name -> median seconds.
    """
    spec = transformer.spec
    generator = torch.Generator().manual_seed(0)
    teacher_length = spec.sequence_length - spec.scales[0] * spec.action_dim
    batch = {
        "obs": torch.randn(batch_size, spec.obs_steps, spec.obs_dim, generator=generator),
        "teacher_inputs": torch.randn(batch_size, teacher_length, spec.latent_channels, generator=generator),
        "token_sequence": torch.randint(spec.codebook_size, (batch_size, spec.sequence_length), generator=generator),
    }
    batch = {name: value.to(device) for name, value in batch.items()}
    copies = {}
    for kernel in ATTENTION_KERNELS:
        copy = deepcopy(transformer).to(device).train()
        copy.attention_kernel = kernel
        copies[kernel] = copy

    def step(copy: CoarseToFineTransformer) -> None:
        with autocast_to(precision, device):
            loss = teacher_forced_step(copy, batch).loss
        loss.backward()
        copy.zero_grad(set_to_none=True)

    devices = [torch.cuda.current_device() if device.index is None else device.index] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        return time_interleaved(
            {kernel: partial(step, copy) for kernel, copy in copies.items()}, device, repeats=repeats
        )


def set_training_attention(transformer: CoarseToFineTransformer, setting: str, run: TrainingRun) -> str:
    """Fix the kernel of `transformer`'s training attention from `setting` (`CarpConfig.attention`) and return it.

    "auto" keeps the kernel of the training state the run resumes, so that a resumed run repeats an uninterrupted
    one exactly; a fresh run times training steps with both kernels (:func:`measure_attention_kernels`) and keeps
    the faster. With several processes, rank 0's choice holds for all.
    """
    if setting not in ATTENTION_SETTINGS:
        raise ValueError(f"attention must be one of {ATTENTION_SETTINGS}, got {setting!r}")
    kernel = setting
    if setting == "auto":
        kernel = _resumed_kernel(Path(run.checkpoint_dir) / CHECKPOINT_NAME)
        if kernel is not None:
            logger.info("attention: auto keeps %s, the kernel of the training state it resumes", kernel)
        else:
            device = resolve_device(str(run.device))
            batch_size = run.training.batch_size
            seconds = measure_attention_kernels(
                transformer, batch_size, device, resolve_precision(run.training.precision, device)
            )
            kernel = faster_kernel(seconds)
            logger.info(
                "attention: auto chose %s (forward + backward at batch %d on %s: masked %.3f s, blockwise %.3f s)",
                kernel,
                batch_size,
                device,
                seconds["masked"],
                seconds["blockwise"],
            )
    index = distributed.value_of_main(ATTENTION_KERNELS.index(kernel), distributed.current_processes())
    transformer.attention_kernel = ATTENTION_KERNELS[index]
    return transformer.attention_kernel


def _resumed_kernel(state_path: Path) -> str | None:
    """The attention kernel recorded in the training state at `state_path`, or None (no state, or none recorded)."""
    if not state_path.exists():
        return None
    try:
        kernel = read_training_state(state_path)["metadata"]["identity"].get(ATTENTION_IDENTITY_KEY)
    except (CheckpointError, KeyError, TypeError, AttributeError):
        return None  # the loop discards or reports an unusable state itself
    return kernel if kernel in ATTENTION_KERNELS else None


def train_carp(policy: CarpPolicy, config: CarpConfig, run: TrainingRun) -> CarpPolicy:
    """Train `policy`'s transformer in the shared loop on its frozen tokenizer's tokens.

    Args:
        policy: an untrained policy, built after `seed_everything(run.training.seed)` for reproducible weights.
        config: CARP's params section (its optimizer and EMA settings; the architecture is the policy's).
        run: the windows, loop settings, state directory and epoch callback. The callback sees `loss` (mean cross
            entropy per token), `token_accuracy`, `token_accuracy_scale_<k>` (k = 1..K), `learning_rate`,
            `epoch_seconds` and `samples_per_second`.

    Returns:
        The trained policy in eval mode on the training device; with `use_ema` it holds the EMA weights.
    """
    # The spec holds the config (the architecture's and the optimizer's settings) and every shape.
    identity = {
        "policy_type": policy.policy_type,
        "spec": policy.spec.to_dict(),
        "tokenizer_sha256": policy.tokenizer_artifact.sha256,
    }
    # The kernel is part of the identity: the two kernels round differently, so a state of the other one cannot
    # continue a run exactly.
    identity[ATTENTION_IDENTITY_KEY] = set_training_attention(policy.transformer, config.attention, run)
    policy.metadata[ATTENTION_IDENTITY_KEY] = identity[ATTENTION_IDENTITY_KEY]
    return run.train_with_loss(
        policy,
        optimizer_recipe(policy.transformer, config),
        identity,
        prepare_data=lambda windows: with_token_targets(policy, windows),
        training_step=lambda batch: teacher_forced_step(
            policy.transformer, batch | {"obs": policy.batch_features(batch)}
        ),
    )
