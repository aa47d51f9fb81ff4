"""Train the coarse-to-fine transformer against a frozen tokenizer, resumable and deterministic on CPU.

Recipe (DESIGN.md section 5, after VAR and the official CARP trainer): teacher forcing with ground-truth tokens, cross
entropy over all L tokens, AdamW (betas 0.9/0.95 as in VAR, no weight decay on biases and embeddings), linear warm-up
then cosine decay per step, optional EMA of the weights.

Because the tokenizer is frozen, the ground-truth token ids and the teacher-forcing inputs of every window never change;
they are computed once before training instead of re-encoding every batch as the official trainer does.

Learning rate: DESIGN.md's rule is 1e-4 x batch / 256 for the paper's 4,000 epochs on a GPU; the CPU budget here is
tens of epochs, so the default peak is 1e-3 with 100 warm-up steps and cosine decay to 1% of the peak. Measured on a
synthetic pick-and-place proxy (default model, 1,536 windows, 96 steps at batch 256), the train loss went from 6.23
to 6.06 in 48 steps at 1e-4, and after 96 steps reached 5.47 at 3e-4, 3.91 at 1e-3 and 2.81 at 3e-3 without
instability (the AdaLN gates start near zero, which keeps the first steps stable at these rates). The default stays at
1e-3 rather than 3e-3 as a margin for the real runs, which are several times longer over few demonstrations; the
rate is a parameter, and 2e-3 to 3e-3 is worth trying when the epoch budget is small.
"""

import hashlib
import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torch import nn
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
from tqdm.auto import tqdm

from carp.config import TrainingConfig
from carp.policies.carp.config import CarpConfig
from carp.policies.carp.layout import TokenLayout
from carp.policies.carp.policy import check_specs_match
from carp.policies.carp.spec import PolicySpec
from carp.policies.carp.transformer import CoarseToFineTransformer
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer
from carp.training.checkpoint import resume_training_state, save_training_state
from carp.training.cross_entropy import blockwise_cross_entropy
from carp.training.loop import NonFiniteLossError, PolicyTrainingData, epoch_order, make_scheduler
from carp.training.runtime import (
    autocast_to,
    precision_name,
    resolve_device,
    resolve_precision,
    seed_everything,
)

logger = logging.getLogger(__name__)

CHECKPOINT_NAME = "policy_training_state.pt"
TOKENIZE_BATCH_SIZE = 4096
ADAM_BETAS = (0.9, 0.95)


@dataclass
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
    """Tokenize (N, H, A) normalized action windows with the frozen tokenizer, in batches."""
    tokenizer.eval()
    sequences, inputs = [], []
    for batch in torch.split(actions, TOKENIZE_BATCH_SIZE):
        token_ids = tokenizer.encode_to_ids(batch)  # K x (b, A, s_k)
        sequences.append(tokenizer.ids_to_sequence(token_ids))  # (b, L)
        inputs.append(tokenizer.teacher_forcing_sequence(token_ids))  # (b, L - s_1 * A, C)
    return TokenTargets(torch.cat(sequences), torch.cat(inputs))


def _check_data(spec: PolicySpec, tokenizer: MultiScaleActionTokenizer, data: PolicyTrainingData) -> None:
    count = data.obs.shape[0]
    if data.obs.dim() != 3 or tuple(data.obs.shape[1:]) != (spec.obs_steps, spec.obs_dim):
        raise ValueError(
            f"obs must have shape (N, To, Do) = (N, {spec.obs_steps}, {spec.obs_dim}), got {tuple(data.obs.shape)}"
        )
    expected_actions = (count, tokenizer.spec.action_horizon, spec.action_dim)
    if tuple(data.actions.shape) != expected_actions:
        raise ValueError(f"actions must have shape (N, H, A) = {expected_actions}, got {tuple(data.actions.shape)}")
    if count == 0:
        raise ValueError("there are no training windows")
    if spec.num_tasks > 0:
        if data.task_ids is None or tuple(data.task_ids.shape) != (count,):
            raise ValueError(f"a multi-task policy needs task_ids of shape (N,) = ({count},)")
        if int(data.task_ids.min()) < 0 or int(data.task_ids.max()) >= spec.num_tasks:
            raise ValueError(f"task_ids must be in [0, {spec.num_tasks})")
    elif data.task_ids is not None:
        raise ValueError("task_ids were given but the policy spec is single-task (num_tasks = 0)")


def make_optimizer(transformer: nn.Module, learning_rate: float, weight_decay: float) -> torch.optim.AdamW:
    """AdamW over the transformer's parameters; weight decay applies to weight matrices only."""
    decayed, undecayed = [], []
    for name, parameter in transformer.named_parameters():
        # Weight matrices decay; biases and the learned embeddings (VAR's no-decay list) do not.
        is_matrix = parameter.dim() > 1 and "embedding" not in name
        (decayed if is_matrix else undecayed).append(parameter)
    groups = [
        {"params": decayed, "weight_decay": weight_decay},
        {"params": undecayed, "weight_decay": 0.0},
    ]
    # The fused kernel updates all parameters in one pass (CPU and CUDA), instead of ~10 small ops per tensor.
    return torch.optim.AdamW(groups, lr=learning_rate, betas=ADAM_BETAS, fused=True)


def teacher_forced_loss(
    transformer: CoarseToFineTransformer,
    obs: torch.Tensor,
    teacher_inputs: torch.Tensor,
    token_sequence: torch.Tensor,
    task_ids: torch.Tensor | None,
    precision: torch.dtype,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean cross entropy over all tokens of a teacher-forced forward pass, and the predicted (argmax) ids.

    Args:
        transformer: the model being trained.
        obs: (b, To, Do) normalized observations.
        teacher_inputs: (b, L - s_1 * A, C) teacher-forcing inputs.
        token_sequence: (b, L) long ground-truth ids.
        task_ids: (b,) long for multi-task policies, else None.
        precision: autocast dtype of the forward pass (`resolve_precision`).

    Returns:
        The scalar float32 loss and the (b, L) long ids of the highest logits.
    """
    with autocast_to(precision, obs.device):
        grouped_logits = transformer(obs, teacher_inputs, task_ids, grouped_by_dimension=True)  # (A, b * L / A, V)
    head = transformer.head
    grouped_targets = head.group(token_sequence)  # (A, b * L / A)
    # Loss in float32 whatever the forward precision; the logits stay in the head's layout and dtype.
    loss = blockwise_cross_entropy(grouped_logits.flatten(0, 1), grouped_targets.flatten())
    # `max(...).indices` rather than `argmax`: same first-maximum ids, 4-6x faster on these bfloat16 logits on CPU.
    predicted = head.ungroup(grouped_logits.detach().max(dim=-1).indices, token_sequence.shape[0])  # (b, L)
    return loss, predicted


def _run_metadata(
    spec: PolicySpec,
    config: CarpConfig,
    training: TrainingConfig,
    epochs: int,
    tokenizer: MultiScaleActionTokenizer,
    data: PolicyTrainingData,
    precision: torch.dtype,
) -> dict:
    # Everything that changes the result; device and checkpoint cadence do not. The precision is the resolved one.
    relevant = asdict(config) | {
        "epochs": epochs,
        "batch_size": training.batch_size,
        "seed": training.seed,
        "precision": precision_name(precision),
    }
    digest = hashlib.sha256()
    tensors = [data.obs, data.actions] + ([data.task_ids] if data.task_ids is not None else [])
    tensors += [value for _, value in sorted(tokenizer.state_dict().items())]
    for tensor in tensors:
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return {"spec": spec.to_dict(), "settings": relevant, "data_and_tokenizer_sha256": digest.hexdigest()}


def _epoch_metrics(
    loss_sum: float, correct: torch.Tensor, count: int, spec: PolicySpec, learning_rate: float, seconds: float
) -> dict[str, float]:
    metrics = {"loss": loss_sum / count, "token_accuracy": float(correct.sum()) / (count * spec.sequence_length)}
    bounds = TokenLayout(spec.action_dim, spec.scales).scale_bounds
    for scale_index, (start, end) in enumerate(bounds):
        metrics[f"token_accuracy_scale_{scale_index + 1}"] = float(correct[start:end].sum()) / (count * (end - start))
    metrics["learning_rate"] = learning_rate
    metrics["epoch_seconds"] = seconds
    metrics["samples_per_second"] = count / seconds
    return metrics


def train_policy(
    spec: PolicySpec,
    tokenizer: MultiScaleActionTokenizer,
    data: PolicyTrainingData,
    config: CarpConfig,
    training: TrainingConfig,
    checkpoint_dir: Path,
    on_epoch_end: Callable[[int, dict[str, float]], None] | None = None,
    epochs: int | None = None,
    device: str | torch.device = "cpu",
) -> CoarseToFineTransformer:
    """Train a transformer, resuming from `checkpoint_dir` if an interrupted run of the same setup left a state there.

    Args:
        spec: transformer architecture; must match the tokenizer (A, scales, C, V).
        tokenizer: trained tokenizer; frozen (not modified).
        data: normalized training windows.
        config: CARP's params section: the optimizer and EMA settings (the architecture is `spec`'s).
        training: the shared loop settings: batch size, seed, checkpoint cadence, precision.
        checkpoint_dir: directory for the training state (`policy_training_state.pt`); created if missing. A state
            from another spec, settings, tokenizer or data is ignored and overwritten, an unusable one (truncated,
            another format version) deleted; either way with a warning, and training starts over.
        on_epoch_end: called as `on_epoch_end(epoch, metrics)` after every epoch (0-based index) with loss (mean
            cross entropy per token), token_accuracy, token_accuracy_scale_<k> (k = 1..K), learning_rate,
            epoch_seconds and samples_per_second. Epochs restored from a training state are
            reported again first, so the callback sees every epoch of a resumed run.
        epochs: passes over the windows; None takes `training.epochs`.
        device: "auto" (cuda if available, else cpu), "cpu", "cuda" or "cuda:<index>".

    Returns:
        The trained transformer in eval mode on the training device; with `use_ema` it holds the EMA weights.

    Raises:
        NonFiniteLossError: the loss became NaN or infinite (the message names the epoch and step).
    """
    check_specs_match(spec, tokenizer.spec)
    _check_data(spec, tokenizer, data)
    device = resolve_device(str(device))
    epochs = training.epochs if epochs is None else epochs
    tokenizer = tokenizer.to(device).eval()
    obs = data.obs.to(device=device, dtype=torch.float32)
    task_ids = data.task_ids.to(device=device, dtype=torch.long) if data.task_ids is not None else None
    targets = compute_token_targets(tokenizer, data.actions.to(device=device, dtype=torch.float32))

    seed_everything(training.seed)
    transformer = CoarseToFineTransformer(spec).to(device)
    ema = None
    if config.use_ema:
        # Parameters only: the transformer's buffers are constant index tables, which averaging would corrupt.
        ema = AveragedModel(transformer, multi_avg_fn=get_ema_multi_avg_fn(config.ema_decay), use_buffers=False)
    # One module holding both so a training state saves and restores them together.
    trained = nn.ModuleDict({"transformer": transformer} | ({"ema": ema} if ema is not None else {}))
    optimizer = make_optimizer(transformer, config.learning_rate, config.weight_decay)
    num_windows = obs.shape[0]
    steps_per_epoch = math.ceil(num_windows / training.batch_size)
    scheduler = make_scheduler(optimizer, epochs * steps_per_epoch, config.warmup_steps)

    checkpoint_path = Path(checkpoint_dir) / CHECKPOINT_NAME
    precision = resolve_precision(training.precision, device)
    logger.info("policy training on %s in %s", device, precision_name(precision))
    metadata = _run_metadata(spec, config, training, epochs, tokenizer, data, precision)
    start_epoch, history = resume_training_state(checkpoint_path, metadata, trained, optimizer, scheduler, on_epoch_end)
    if start_epoch > 0:
        logger.info("resuming policy training from %s at epoch %d", checkpoint_path, start_epoch)

    for epoch in range(start_epoch, epochs):
        transformer.train()
        started = time.perf_counter()
        loss_sum = 0.0
        correct = torch.zeros(spec.sequence_length, dtype=torch.long, device=device)
        order = epoch_order(training.seed, epoch, num_windows).to(device)
        progress = tqdm(torch.split(order, training.batch_size), desc=f"policy epoch {epoch + 1}/{epochs}", leave=False)
        for step, batch in enumerate(progress):
            batch_targets = targets.token_sequence[batch]  # (b, L)
            loss, predicted = teacher_forced_loss(
                transformer,
                obs[batch],
                targets.teacher_inputs[batch],
                batch_targets,
                task_ids[batch] if task_ids is not None else None,
                precision,
            )
            loss_value = float(loss.detach())
            if not math.isfinite(loss_value):
                raise NonFiniteLossError(
                    f"policy training loss is {loss_value} at epoch {epoch + 1}, step {step + 1} of {steps_per_epoch}"
                    f" (learning rate {optimizer.param_groups[0]['lr']:.3g})"
                )
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            scheduler.step()
            if ema is not None:
                ema.update_parameters(transformer)
            loss_sum += loss_value * batch.numel()
            correct += (predicted == batch_targets).sum(dim=0)
            progress.set_postfix(loss=f"{loss_value:.4f}")
        metrics = _epoch_metrics(
            loss_sum, correct, num_windows, spec, optimizer.param_groups[0]["lr"], time.perf_counter() - started
        )
        history.append(metrics)
        if (epoch + 1) % training.checkpoint_every == 0 or epoch + 1 == epochs:
            save_training_state(checkpoint_path, trained, optimizer, scheduler, epoch + 1, metadata, history)
        logger.info(
            "policy epoch %d/%d: %s",
            epoch + 1,
            epochs,
            ", ".join(f"{key}={value:.4g}" for key, value in metrics.items()),
        )
        if on_epoch_end is not None:
            on_epoch_end(epoch, metrics)
    if ema is not None:
        transformer.load_state_dict(ema.module.state_dict())
    return transformer.eval()
