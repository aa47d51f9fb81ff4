"""Train the multi-scale action tokenizer on normalized action windows, resumable and deterministic on CPU.

Recipe: AdamW (no weight decay on biases, norms and the codebook), linear warm-up then cosine decay per step,
random per-dimension rescaling and moving of training windows (`augment_windows`), shuffling, augmentation and code
restarts drawn from generators seeded by (seed, epoch) so a resumed run repeats an uninterrupted one exactly. Its
settings are the `tokenizer` params section (`carp.config.TokenizerConfig`), sized for a 2-core CPU; the paper's 300
epochs at batch 256 assume a GPU.

Why it keeps its own loop rather than the policies' (`carp.training.loop`): besides a loss per batch it initializes
the codebook from data before the first epoch (not on resuming), draws a new augmentation of all windows every
epoch, re-seeds dead codes from each epoch's code counts, measures the held-out reconstruction after each epoch, and
decays its learning rate to 5% rather than 1% of the peak. It shares the training-state files
(`carp.training.checkpoint`), seeding and device selection (`carp.training.runtime`).

Augmentation: min-max normalization puts the most extreme episode, possibly a held-out one, at -1 or 1, and a
rotation column that is constant after the first steps sits at a new level in every episode; held-out error is
then dominated by levels and amplitudes no training episode shows. Rescaled and moved copies teach each dimension's
VQ-VAE to encode any level and a range of amplitudes.

Dead codes: a VQ codebook trained from random codes leaves many codes unused, which wastes capacity and makes the
reconstruction coarse. Two remedies, both per action dimension:
- Data-dependent initialization: before the first step every code is set to a vector the nearest-code search
  actually sees (the area-downsampled residual at some scale for some training window).
- Restarts: after each epoch in the first `restart_fraction` of training, codes that no training token used during
  that epoch are re-seeded the same way. Restarts stop early so the final epochs fine-tune a stable codebook.
Cosine search keeps even a random codebook partly alive, so the gain of the two is moderate, but it shows in both
the held-out error and the codebook's perplexity.
"""

import hashlib
import logging
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict
from pathlib import Path

import torch
from tqdm.auto import tqdm

from carp.config.tokenizer import TokenizerConfig
from carp.tokenizer.artifact import NonFiniteTokenizerError
from carp.tokenizer.metrics import count_codes
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer
from carp.training.checkpoint import resume_training_state, save_training_state
from carp.training.runtime import resolve_device, seed_everything

logger = logging.getLogger(__name__)

CHECKPOINT_NAME = "tokenizer_training_state.pt"
# Metrics that must stay finite: once one is NaN or inf the weights are too, and every later epoch stays so.
LOSS_METRICS = ("train_loss", "train_reconstruction_mse", "train_vq_loss", "valid_reconstruction_mse")
# Windows whose residuals seed the codebook; enough candidates for V = 512 codes at every scale.
RESTART_CANDIDATE_WINDOWS = 1024
EVALUATION_BATCH_SIZE = 2048


def _epoch_generator(seed: int, epoch: int, stream: int) -> torch.Generator:
    # Independent, reproducible streams per (epoch, purpose) that do not depend on how much randomness earlier
    # epochs consumed, which is what makes resuming exact. Epoch -1 is the initialization before training.
    return torch.Generator().manual_seed(seed * 1_000_003 + (epoch + 1) * 16 + stream)


def _make_optimizer(tokenizer: MultiScaleActionTokenizer, config: TokenizerConfig) -> torch.optim.AdamW:
    decayed, undecayed = [], []
    for name, parameter in tokenizer.named_parameters():
        # Conv kernels decay; biases, norm affines and the codebook (whose scale is the latent's scale) do not.
        is_kernel = parameter.dim() > 1 and not name.endswith("codebook")
        (decayed if is_kernel else undecayed).append(parameter)
    groups = [
        {"params": decayed, "weight_decay": config.weight_decay},
        {"params": undecayed, "weight_decay": 0.0},
    ]
    # The fused kernel updates all tensors in one pass, much cheaper per step on CPU than the default; same update.
    return torch.optim.AdamW(groups, lr=config.learning_rate, fused=True)


def _make_scheduler(
    optimizer: torch.optim.Optimizer, total_steps: int, warmup_fraction: float
) -> torch.optim.lr_scheduler.LambdaLR:
    warmup_steps = max(1, round(total_steps * warmup_fraction))

    def factor(step: int) -> float:
        if step < warmup_steps:
            return (step + 1) / warmup_steps
        progress = (step - warmup_steps) / max(1, total_steps - warmup_steps)
        # Decay to 5% of the peak rather than 0 so the last steps still move the codebook.
        return 0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * min(progress, 1.0)))

    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)


def augment_windows(
    windows: torch.Tensor, probability: float, max_scale: float, generator: torch.Generator
) -> torch.Tensor:
    """Randomly rescale and move each (window, dimension) with the given probability, staying inside [-1, 1].

    Why: held-out demos reach levels and amplitudes the training demos never show (a rotation column that is constant
    after the first steps sits at a new value in every episode, and min-max normalization puts the most extreme
    episode, possibly a held-out one, at -1 or 1). Transformed copies teach each dimension's VQ-VAE to encode any
    level and a range of amplitudes, not only those of the training episodes.

    Args:
        windows: (N, H, A) normalized windows.
        probability: chance that a given window's dimension is transformed.
        max_scale: amplitudes are multiplied by a factor log-uniform in [1 / max_scale, max_scale] (1 = moves only),
            capped so that the window still fits into [-1, 1].
        generator: CPU generator making the draw reproducible.

    Returns:
        (N, H, A) windows; a transformed window's centre is then placed uniformly where the window fits into [-1, 1].
    """
    if probability == 0.0:
        return windows
    count, _, num_dimensions = windows.shape
    draws = torch.rand(3, count, num_dimensions, generator=generator).to(windows.device)  # (3, N, A)
    highest, lowest = windows.amax(dim=1), windows.amin(dim=1)  # (N, A)
    centre, half_span = (highest + lowest) / 2, (highest - lowest) / 2
    log_scale = math.log(max_scale) * (2 * draws[0] - 1)
    scale = torch.minimum(log_scale.exp(), 1 / half_span.clamp(min=1e-6))  # the window must still fit into [-1, 1]
    room = (1 - scale * half_span).clamp(min=0.0)  # how far the new centre may sit from 0
    new_centre = room * (2 * draws[1] - 1)
    transformed = (windows - centre[:, None, :]) * scale[:, None, :] + new_centre[:, None, :]
    chosen = draws[2] < probability  # (N, A)
    return torch.where(chosen[:, None, :], transformed, windows)


def _check_windows(name: str, windows: torch.Tensor, spec: TokenizerSpec) -> None:
    expected = (spec.action_horizon, spec.action_dim)
    if windows.dim() != 3 or tuple(windows.shape[1:]) != expected:
        raise ValueError(
            f"{name} must have shape (N, H, A) = (N, {expected[0]}, {expected[1]}), got {tuple(windows.shape)}"
        )


NON_TRAINING_FIELDS = (
    "source",
    "tasks",
    "registry_alias",
    "checkpoint_every",
    "latent_channels",
    "base_channels",
    "channel_mult",
    "commitment_weight",
    "kind",
)
"""Fields of the params section outside a run's training settings: the kind (this trainer trains the default kind
whatever it says), where the tokenizer comes from and is registered,
the checkpoint cadence (neither changes the result), and the architecture, which the spec holds; the tasks count
through the training windows."""


def _run_metadata(spec: TokenizerSpec, config: TokenizerConfig, train_windows: torch.Tensor) -> dict:
    # Everything that changes the result; the device does not.
    relevant = {key: value for key, value in asdict(config).items() if key not in NON_TRAINING_FIELDS}
    data_hash = hashlib.sha256(train_windows.detach().cpu().contiguous().numpy().tobytes()).hexdigest()
    return {"spec": spec.to_dict(), "settings": relevant, "train_windows_sha256": data_hash}


@torch.no_grad()
def _restart_unused_codes(
    tokenizer: MultiScaleActionTokenizer,
    train_windows: torch.Tensor,
    unused: torch.Tensor,
    generator: torch.Generator,
) -> int:
    if not bool(unused.any()):
        return 0
    was_training = tokenizer.training
    tokenizer.eval()
    count = min(RESTART_CANDIDATE_WINDOWS, train_windows.shape[0])
    chosen = torch.randperm(train_windows.shape[0], generator=generator)[:count]
    latent = tokenizer.encode_to_latent(train_windows[chosen.to(train_windows.device)])  # (n, A, C, l)
    candidates = tokenizer.quantizer.residual_vectors(latent)  # (A, n * sum(s_k), C)
    restarted = tokenizer.quantizer.restart_codes(unused, candidates, generator)
    tokenizer.train(was_training)
    return restarted


def _train_epoch(
    tokenizer: MultiScaleActionTokenizer,
    optimizer: torch.optim.Optimizer,
    scheduler: torch.optim.lr_scheduler.LRScheduler,
    train_windows: torch.Tensor,
    batches: Iterable[torch.Tensor],
) -> tuple[dict[str, float], torch.Tensor]:
    """One pass over `batches` of window indices; returns window-weighted mean losses and code counts (A, V)."""
    spec = tokenizer.spec
    code_counts = torch.zeros(spec.action_dim, spec.codebook_size, dtype=torch.long, device=train_windows.device)
    totals = {"train_loss": 0.0, "train_reconstruction_mse": 0.0, "train_vq_loss": 0.0}
    for batch_indices in batches:
        output = tokenizer(train_windows[batch_indices])
        optimizer.zero_grad(set_to_none=True)
        output.loss.backward()
        optimizer.step()
        scheduler.step()
        for ids in output.token_ids:
            code_counts += count_codes(ids, spec.codebook_size)
        share = batch_indices.numel() / train_windows.shape[0]
        totals["train_loss"] += share * output.loss.item()
        totals["train_reconstruction_mse"] += share * output.reconstruction_loss.item()
        totals["train_vq_loss"] += share * output.vq_loss.item()
    return totals, code_counts


@torch.no_grad()
def evaluate_reconstruction_mse(tokenizer: MultiScaleActionTokenizer, windows: torch.Tensor) -> float:
    """Mean squared error (normalized units) of encode -> ids -> decode over (N, H, A) windows."""
    was_training = tokenizer.training
    tokenizer.eval()
    squared_error, count = 0.0, 0
    for batch in torch.split(windows, EVALUATION_BATCH_SIZE):
        reconstruction = tokenizer.decode_ids(tokenizer.encode_to_ids(batch))  # (b, H, A)
        squared_error += float(((reconstruction - batch) ** 2).sum())
        count += batch.numel()
    tokenizer.train(was_training)
    return squared_error / max(count, 1)


def _resume_or_initialize(
    tokenizer: MultiScaleActionTokenizer,
    optimizer: torch.optim.Optimizer,
    scheduler: torch.optim.lr_scheduler.LRScheduler,
    checkpoint_path: Path,
    metadata: dict,
    train_windows: torch.Tensor,
    seed: int,
    on_epoch_end: Callable[[int, dict[str, float]], None] | None,
) -> tuple[int, list[dict[str, float]]]:
    """Resume a matching training state (its epochs reported again), or seed the whole codebook from data.

    Returns:
        The epoch to continue from and the metrics of the epochs before it.
    """
    start_epoch, history = resume_training_state(
        checkpoint_path, metadata, tokenizer, optimizer, scheduler, on_epoch_end
    )
    if start_epoch > 0:
        logger.info("resuming tokenizer training from %s at epoch %d", checkpoint_path, start_epoch)
        return start_epoch, history
    spec = tokenizer.spec
    all_codes = torch.ones(spec.action_dim, spec.codebook_size, dtype=torch.bool)
    _restart_unused_codes(tokenizer, train_windows, all_codes, _epoch_generator(seed, -1, 0))
    return 0, []


def _require_finite_losses(metrics: dict[str, float], epoch: int, epochs: int) -> None:
    for key in LOSS_METRICS:
        if key in metrics and not math.isfinite(metrics[key]):
            raise NonFiniteTokenizerError(
                f"tokenizer training epoch {epoch + 1}/{epochs}: {key}={metrics[key]!r}: not finite (training "
                "diverged: lower the learning rate, or check the actions' ranges)"
            )


def train_tokenizer(
    spec: TokenizerSpec,
    train_windows: torch.Tensor,
    valid_windows: torch.Tensor,
    config: TokenizerConfig,
    checkpoint_dir: Path,
    on_epoch_end: Callable[[int, dict[str, float]], None] | None = None,
    device: str | torch.device = "cpu",
) -> MultiScaleActionTokenizer:
    """Train a tokenizer, resuming from `checkpoint_dir` if an interrupted run of the same setup left a state there.

    Args:
        spec: architecture.
        train_windows: (N, H, A) float normalized action windows.
        valid_windows: (M, H, A) float normalized held-out windows (M may be 0).
        config: the `tokenizer` params section: its training settings (the architecture is `spec`'s).
        checkpoint_dir: directory for the training state (`tokenizer_training_state.pt`); created if missing. A state
            from a different spec, settings or training data is ignored and overwritten, an unusable one (truncated,
            another format version) deleted; either way with a warning, and training starts over.
        on_epoch_end: called as `on_epoch_end(epoch, metrics)` after every epoch (0-based epoch index) with
            train_loss, train_reconstruction_mse, train_vq_loss, valid_reconstruction_mse (if M > 0),
            learning_rate, restarted_codes and epoch_seconds. Epochs restored from a training state are
            reported again first, so the callback sees every epoch of a resumed run.
        device: "auto" (cuda if available, else cpu), "cpu", "cuda" or "cuda:<index>".

    Returns:
        The trained tokenizer in eval mode, on the training device.

    Raises:
        carp.tokenizer.artifact.NonFiniteTokenizerError: an epoch's loss or held-out error is NaN or inf; raised
            before that epoch's training state is saved.
    """
    _check_windows("train_windows", train_windows, spec)
    _check_windows("valid_windows", valid_windows, spec)
    if train_windows.shape[0] == 0:
        raise ValueError("train_windows is empty")
    device = resolve_device(str(device))
    train_windows = train_windows.to(device=device, dtype=torch.float32)
    valid_windows = valid_windows.to(device=device, dtype=torch.float32)

    seed_everything(config.seed)
    tokenizer = MultiScaleActionTokenizer(spec).to(device)
    optimizer = _make_optimizer(tokenizer, config)
    num_windows = train_windows.shape[0]
    steps_per_epoch = math.ceil(num_windows / config.batch_size)
    scheduler = _make_scheduler(optimizer, config.epochs * steps_per_epoch, config.warmup_fraction)

    checkpoint_path = Path(checkpoint_dir) / CHECKPOINT_NAME
    metadata = _run_metadata(spec, config, train_windows)
    start_epoch, history = _resume_or_initialize(
        tokenizer, optimizer, scheduler, checkpoint_path, metadata, train_windows, config.seed, on_epoch_end
    )

    restart_epochs = math.floor(config.epochs * config.restart_fraction)
    tokenizer.train()
    for epoch in range(start_epoch, config.epochs):
        started = time.perf_counter()
        order = torch.randperm(num_windows, generator=_epoch_generator(config.seed, epoch, 1)).to(device)
        progress = tqdm(
            torch.split(order, config.batch_size),
            desc=f"tokenizer epoch {epoch + 1}/{config.epochs}",
            leave=False,
        )
        epoch_windows = augment_windows(
            train_windows,
            config.augment_probability,
            config.augment_max_scale,
            _epoch_generator(config.seed, epoch, 3),
        )
        totals, code_counts = _train_epoch(tokenizer, optimizer, scheduler, epoch_windows, progress)
        restarted = 0
        if epoch < restart_epochs:
            restarted = _restart_unused_codes(
                tokenizer, train_windows, (code_counts == 0).cpu(), _epoch_generator(config.seed, epoch, 2)
            )
        metrics = dict(totals)
        if valid_windows.shape[0] > 0:
            metrics["valid_reconstruction_mse"] = evaluate_reconstruction_mse(tokenizer, valid_windows)
        metrics["learning_rate"] = optimizer.param_groups[0]["lr"]
        metrics["restarted_codes"] = float(restarted)
        metrics["epoch_seconds"] = time.perf_counter() - started
        _require_finite_losses(metrics, epoch, config.epochs)
        history.append(metrics)
        if (epoch + 1) % config.checkpoint_every == 0 or epoch + 1 == config.epochs:
            save_training_state(checkpoint_path, tokenizer, optimizer, scheduler, epoch + 1, metadata, history)
        logger.info(
            "tokenizer epoch %d/%d: %s",
            epoch + 1,
            config.epochs,
            ", ".join(f"{key}={value:.4g}" for key, value in metrics.items()),
        )
        if on_epoch_end is not None:
            on_epoch_end(epoch, metrics)
    return tokenizer.eval()
