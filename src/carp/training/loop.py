"""The resumable training loop policy families plug their loss into.

A family hands over an untrained policy (`carp.policies.base.Policy`, whose `training_loss(batch)` is the only
family-specific step) and its optimizer recipe; the loop owns what every family needs alike: a seeded shuffle per
epoch (independent of earlier epochs, so a resumed run is exact), AdamW with linear warm-up then cosine decay, an
optional EMA of the weights (the family's averaging rule), autocast precision, a progress bar, a training state every
`checkpoint_every` epochs that an interrupted run of the same setup resumes from
(`carp.training.checkpoint`), per-epoch metrics for tracking, and a clear error when the loss stops being finite.
Under a process group (torchrun) the processes share every batch (`carp.training.distributed`).

Two optional hooks cover what a family needs beyond a loss: `prepare_data` derives per-window tensors once before the
first epoch (CARP tokenizes every window with its frozen tokenizer instead of once per batch), and `training_step`
returns, besides the loss, sums of per-window metrics over the batch that the loop turns into epoch means (CARP's
token accuracies).
"""

import copy
import hashlib
import logging
import math
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn
from torch.optim.swa_utils import AveragedModel
from tqdm.auto import tqdm

from carp.policies.base import Policy
from carp.training import distributed
from carp.training.checkpoint import resume_training_state, save_training_state
from carp.training.runtime import autocast_to, precision_name, resolve_device, resolve_precision

if TYPE_CHECKING:
    from carp.training.run import TrainingRun

logger = logging.getLogger(__name__)

CHECKPOINT_NAME = "training_state.pt"
SNAPSHOT_DIRNAME = "snapshots"


def snapshot_path(directory: Path, epoch: int) -> Path:
    """``<directory>/epoch<NNNN>.pt``: the policy snapshot kept after `epoch` (1-based)."""
    return Path(directory) / f"epoch{epoch:04d}.pt"


FINAL_LEARNING_RATE_FRACTION = 0.01
FUSED_ADAMW_DEVICES = ("cpu", "cuda")
"""Device types with PyTorch's fused AdamW kernel, which updates every parameter in one pass instead of ~10 small
operations per tensor."""


class NonFiniteLossError(FloatingPointError):
    """The training loss became NaN or infinite."""


@dataclass
class PolicyTrainingData:
    """Normalized training windows.

    Attributes:
        obs: (N, To, Do) float normalized observations.
        actions: (N, H, A) float normalized actions.
        task_ids: (N,) long task indices for multi-task policies, else None.
        extras: (N, ...) tensors a family derives from the windows once (`train_with_loss`'s `prepare_data`), by
            name; every batch carries their rows under the same names.
        images: for image policies, reads the camera images of some windows: (b,) window indices -> (b, To,
            cameras, 3, h, w) uint8 (e.g. `carp.data.image_windows.ImageWindowReader.images`); they stay on disk
            and each batch reads its own. None for state policies.
    """

    obs: torch.Tensor
    actions: torch.Tensor
    task_ids: torch.Tensor | None = None
    extras: dict[str, torch.Tensor] = field(default_factory=dict)
    images: Callable[[np.ndarray], np.ndarray] | None = None

    def batch(self, indices: torch.Tensor) -> dict[str, torch.Tensor]:
        """The windows at `indices` (b,) as a training batch.

        Holds `obs`, `actions`, `task_ids` if any, the extras, and `images` (on the device of `obs`) when the windows
        have them.
        """
        batch = {"obs": self.obs[indices], "actions": self.actions[indices]}
        if self.task_ids is not None:
            batch["task_ids"] = self.task_ids[indices]
        for name, values in self.extras.items():
            batch[name] = values[indices]
        if self.images is not None:
            batch["images"] = torch.from_numpy(self.images(indices.cpu().numpy())).to(self.obs.device)
        return batch

    def to(self, device: torch.device) -> "PolicyTrainingData":
        """The windows on `device`: observations and actions float32, task ids long, extras in their own dtype."""
        return PolicyTrainingData(
            self.obs.to(device=device, dtype=torch.float32),
            self.actions.to(device=device, dtype=torch.float32),
            self.task_ids.to(device=device, dtype=torch.long) if self.task_ids is not None else None,
            {name: values.to(device) for name, values in self.extras.items()},
            self.images,
        )


def check_task_ids(data: PolicyTrainingData, num_tasks: int) -> None:
    """Raise ValueError unless `data` has one task id in [0, num_tasks) per window, or none for a single-task policy.

    Args:
        data: the training windows.
        num_tasks: the policy's task count; 0 for a single-task policy.
    """
    count = data.obs.shape[0]
    if num_tasks == 0:
        if data.task_ids is not None:
            raise ValueError("task_ids were given but the policy is single-task")
        return
    if data.task_ids is None or tuple(data.task_ids.shape) != (count,):
        raise ValueError(f"a multi-task policy needs task_ids of shape (N,) = ({count},)")
    if count and (int(data.task_ids.min()) < 0 or int(data.task_ids.max()) >= num_tasks):
        raise ValueError(f"task_ids must be in [0, {num_tasks})")


@dataclass(frozen=True)
class TrainingStep:
    """What a family's training step returns for one batch.

    Attributes:
        loss: scalar loss to minimize (float32, or cast to it by the loop).
        metric_sums: name -> scalar tensor, the sum over the batch's windows of a per-window metric (e.g. the
            fraction of a window's tokens predicted right); the loop reports each as its mean over the epoch's
            windows. Accumulated on the device, so no step waits for them.
    """

    loss: torch.Tensor
    metric_sums: dict[str, torch.Tensor] = field(default_factory=dict)


@dataclass(frozen=True)
class OptimizerRecipe:
    """A family's optimizer and weight averaging.

    Attributes:
        learning_rate: peak AdamW learning rate.
        weight_decay: AdamW weight decay (of every trained parameter).
        warmup_steps: optimizer steps of linear warm-up before the cosine decay to 1% of the peak.
        betas: AdamW betas.
        ema: builds the weight average of the trained module (e.g. `carp.policies.diffusion.ema`), or None.
        parameter_groups: returns AdamW parameter groups (each with its own `weight_decay`) when the family decays
            some parameters and not others; trainable parameters of the policy that no group holds (a camera
            encoder) train with `weight_decay`. None trains every parameter that requires gradients with
            `weight_decay`.
    """

    learning_rate: float
    weight_decay: float = 0.0
    warmup_steps: int = 0
    betas: tuple[float, float] = (0.9, 0.999)
    ema: Callable[[nn.Module], AveragedModel] | None = None
    parameter_groups: Callable[[], list[dict]] | None = None


def matrix_decay_groups(module: nn.Module, weight_decay: float) -> list[dict]:
    """AdamW parameter groups in which weight matrices decay and biases, norms and learned embeddings do not.

    VAR's rule (its no-decay list), which CARP and the next-token baseline share: a parameter decays when it has
    more than one dimension and its name does not contain `embedding`. Frozen parameters are left out.
    """
    decayed, undecayed = [], []
    for name, parameter in module.named_parameters():
        if not parameter.requires_grad:
            continue
        is_matrix = parameter.dim() > 1 and "embedding" not in name
        (decayed if is_matrix else undecayed).append(parameter)
    return [{"params": decayed, "weight_decay": weight_decay}, {"params": undecayed, "weight_decay": 0.0}]


def make_optimizer(parameters: list, recipe: OptimizerRecipe, device: torch.device) -> torch.optim.AdamW:
    """AdamW at the recipe's peak rate and betas over `parameters` (tensors or groups), fused where `device` has it."""
    return torch.optim.AdamW(
        parameters,
        lr=recipe.learning_rate,
        betas=recipe.betas,
        weight_decay=recipe.weight_decay,
        fused=device.type in FUSED_ADAMW_DEVICES,
    )


def make_scheduler(
    optimizer: torch.optim.Optimizer, total_steps: int, warmup_steps: int
) -> torch.optim.lr_scheduler.LRScheduler:
    """Linear warm-up over `warmup_steps`, then cosine decay to 1% of the peak at `total_steps`."""
    warmup_steps = min(warmup_steps, total_steps - 1)
    cosine = torch.optim.lr_scheduler.CosineAnnealingLR(
        optimizer,
        T_max=max(1, total_steps - warmup_steps),
        eta_min=optimizer.param_groups[0]["lr"] * FINAL_LEARNING_RATE_FRACTION,
    )
    if warmup_steps <= 0:
        return cosine
    warmup = torch.optim.lr_scheduler.LinearLR(optimizer, start_factor=1.0 / warmup_steps, total_iters=warmup_steps)
    return torch.optim.lr_scheduler.SequentialLR(optimizer, [warmup, cosine], milestones=[warmup_steps])


def epoch_order(seed: int, epoch: int, count: int) -> torch.Tensor:
    """Shuffled window indices (count,) of `epoch`; a generator per epoch makes resuming exact."""
    return torch.randperm(count, generator=torch.Generator().manual_seed(seed * 1_000_003 + epoch))


def data_digest(data: PolicyTrainingData) -> str:
    """sha256 of the training windows, part of a run's identity for resuming."""
    digest = hashlib.sha256()
    for tensor in [data.obs, data.actions] + ([data.task_ids] if data.task_ids is not None else []):
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def save_snapshot(policy: Policy, ema: AveragedModel | None, path: Path) -> None:
    """Save `policy` as evaluation would load it: with the averaged weights of `ema` when there is one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if ema is None:
        policy.save(path)
        return
    averaged = copy.deepcopy(policy)
    averaged.load_state_dict(ema.module.state_dict())
    averaged.save(path)


def _loss_only(policy: Policy) -> Callable[[dict[str, torch.Tensor]], TrainingStep]:
    def step(batch: dict[str, torch.Tensor]) -> TrainingStep:
        return TrainingStep(policy.training_loss(batch))

    return step


def train_with_loss(
    policy: Policy,
    run: "TrainingRun",
    recipe: OptimizerRecipe,
    run_identity: dict[str, Any],
    prepare_data: Callable[[PolicyTrainingData], PolicyTrainingData] | None = None,
    training_step: Callable[[dict[str, torch.Tensor]], TrainingStep] | None = None,
) -> Policy:
    """Train `policy` on its own `training_loss`; resume from the run's checkpoint folder if this setup left a state.

    Args:
        policy: an untrained policy; its parameters that require gradients are trained. Initialize it after
            `seed_everything(training.seed)` for reproducible weights (the family's `train` does).
        run: the training run (`carp.training.run.TrainingRun`): its normalized windows (`data`), the shared loop
            settings (`training`: batch size, seed, checkpoint cadence, precision; `epochs` unless the run gives
            them), the folder of the training state (`checkpoint_dir`, created if missing; a state of another setup
            is ignored and overwritten, an unusable one deleted, each with a warning), the device ("auto", "cpu",
            "cuda" or "cuda:<index>") and `on_epoch_end`, called as `on_epoch_end(epoch, metrics)` after every epoch
            (0-based) with `loss` (mean over windows), the means of the training step's metric sums,
            `learning_rate`, `epoch_seconds` and `samples_per_second` (a resumed run reports its stored epochs
            first; called on rank 0 only when several processes train).
        recipe: the family's optimizer and weight averaging.
        run_identity: plain values that, with the data and the loop settings, identify the run (the family's
            config and shapes); a stored state resumes only if they match.
        prepare_data: called once with the windows on the training device (after the policy moved there), outside
            autocast; returns them with the family's extras (e.g. token targets), or refuses them with ValueError.
            None trains on the windows as given.
        training_step: the loss and metric sums of one batch (see `PolicyTrainingData.batch`), run under the loop's
            autocast; None takes `policy.training_loss` and no metrics.

    After each epoch of `training.snapshot_epochs(epochs)` the policy as evaluation would see it (the EMA weights
    where the family averages) is saved to ``<checkpoint_dir>/snapshots/epoch<NNNN>.pt`` (`snapshot_path`), for
    checkpoint selection. They live beside the training state so that a resumed run keeps the earlier ones; a run
    that starts from its first epoch clears them.

    Several processes (a process group started by `carp.training.distributed.start_process_group`, each process
    calling this function with the same arguments) take the same optimizer steps as one: each trains on its share of
    every batch of `training.batch_size` windows with its gradients averaged over the processes, and the metric sums
    are added over the processes. Rank 0 alone reports epochs and writes the training state; every process resumes
    from the same one.

    Returns:
        The trained policy in eval mode on `device`; with an EMA it holds the averaged weights.

    Raises:
        NonFiniteLossError: the loss became NaN or infinite (the message names the epoch and step).
    """
    training, data, checkpoint_dir, on_epoch_end = run.training, run.data, run.checkpoint_dir, run.on_epoch_end
    epochs = training.epochs if run.epochs is None else run.epochs
    device = resolve_device(str(run.device))
    policy = policy.to(device)
    count = data.obs.shape[0]
    if count == 0:
        raise ValueError("there are no training windows")
    data = data.to(device)
    # Digest of the windows as given: whatever `prepare_data` derives from them follows from the run identity.
    digest = data_digest(data)
    if prepare_data is not None:
        data = prepare_data(data)
    trainable = nn.ModuleDict({"policy": policy})  # type: ignore[dict-item]  (every family is an nn.Module)
    ema = recipe.ema(policy) if recipe.ema is not None else None
    if ema is not None:
        trainable["ema"] = ema
    if recipe.parameter_groups is not None:
        parameters = recipe.parameter_groups()
        # A family groups its own network; what it leaves out (an image policy's camera encoder) still trains.
        grouped = {id(parameter) for group in parameters for parameter in group["params"]}
        rest = [p for p in policy.parameters() if p.requires_grad and id(p) not in grouped]
        if rest:
            parameters.append({"params": rest, "weight_decay": recipe.weight_decay})
    else:
        parameters = [parameter for parameter in policy.parameters() if parameter.requires_grad]
    optimizer = make_optimizer(parameters, recipe, device)
    steps_per_epoch = math.ceil(count / training.batch_size)
    scheduler = make_scheduler(optimizer, epochs * steps_per_epoch, recipe.warmup_steps)
    precision = resolve_precision(training.precision, device)
    metadata = {
        "identity": run_identity,
        "loop": {
            "epochs": epochs,
            "batch_size": training.batch_size,
            "seed": training.seed,
            "precision": precision_name(precision),
        },
        "recipe": {key: value for key, value in vars(recipe).items() if not callable(value)}
        | {"ema": ema is not None, "parameter_groups": recipe.parameter_groups is not None},
        "data_sha256": digest,
    }
    if training.snapshot_epochs(epochs):
        # Snapshots of epochs a finished run did not keep cannot be made afterwards: another set retrains.
        metadata["loop"]["snapshot_epochs"] = list(training.snapshot_epochs(epochs))
    processes = distributed.current_processes()
    if processes.is_distributed:
        # Per-process random draws make a state resume exactly only on as many processes as wrote it.
        metadata["loop"]["processes"] = processes.world_size
    if not processes.is_main:
        on_epoch_end = None
    checkpoint_path = Path(checkpoint_dir) / CHECKPOINT_NAME
    start_epoch, history = distributed.main_process_first(
        lambda: resume_training_state(checkpoint_path, metadata, trainable, optimizer, scheduler, on_epoch_end),
        processes,
    )
    distributed.require_same(start_epoch, "epoch to resume at", processes)
    step_of = distributed.step_function(policy, training_step or _loss_only(policy), processes)
    if start_epoch > 0:
        logger.info("resuming %s training from %s at epoch %d", policy.policy_type, checkpoint_path, start_epoch)
    snapshot_dir = Path(checkpoint_dir) / SNAPSHOT_DIRNAME
    snapshot_epochs = set(training.snapshot_epochs(epochs))
    if processes.is_main and start_epoch == 0:
        shutil.rmtree(snapshot_dir, ignore_errors=True)
    for epoch in range(start_epoch, epochs):
        policy.train()
        started = time.perf_counter()
        loss_sum = 0.0
        metric_sums: dict[str, torch.Tensor] = {}
        distributed.seed_epoch(training.seed, epoch, processes)
        order = epoch_order(training.seed, epoch, count).to(device)
        progress = tqdm(
            torch.split(order, training.batch_size),
            desc=f"{policy.policy_type} epoch {epoch + 1}/{epochs}",
            leave=False,
            disable=not processes.is_main,
        )
        for step, indices in enumerate(progress):
            share, weight = distributed.batch_share(indices, processes)
            with autocast_to(precision, device):
                step_result = step_of(data.batch(share))
            loss = step_result.loss.float() * weight
            loss_value = distributed.mean_over_processes(loss.detach(), processes)
            if not math.isfinite(loss_value):
                raise NonFiniteLossError(
                    f"{policy.policy_type} training loss is {loss_value} at epoch {epoch + 1}, step {step + 1} of "
                    f"{steps_per_epoch} (learning rate {optimizer.param_groups[0]['lr']:.3g})"
                )
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            scheduler.step()
            if ema is not None:
                ema.update_parameters(policy)
            loss_sum += loss_value * indices.numel()
            for name, value in step_result.metric_sums.items():
                # float64: an epoch's sum of per-window fractions stays exact to far below the reported digits. A
                # process without windows in this batch (weight 0) stood in with one window; it adds nothing.
                metric_sums[name] = metric_sums.get(name, 0.0) + value.detach().to(torch.float64) * (weight > 0)
            progress.set_postfix(loss=f"{loss_value:.4f}")
        seconds = time.perf_counter() - started
        metrics = {
            "loss": loss_sum / count,
            **{name: total / count for name, total in distributed.sums_over_processes(metric_sums, processes).items()},
            "learning_rate": optimizer.param_groups[0]["lr"],
            "epoch_seconds": seconds,
            "samples_per_second": count / seconds,
        }
        history.append(metrics)
        if processes.is_main and epoch + 1 in snapshot_epochs:
            save_snapshot(policy, ema, snapshot_path(snapshot_dir, epoch + 1))
        if processes.is_main and ((epoch + 1) % training.checkpoint_every == 0 or epoch + 1 == epochs):
            save_training_state(checkpoint_path, trainable, optimizer, scheduler, epoch + 1, metadata, history)
        logger.info(
            "%s epoch %d/%d: %s",
            policy.policy_type,
            epoch + 1,
            epochs,
            ", ".join(f"{key}={value:.4g}" for key, value in metrics.items()),
        )
        if on_epoch_end is not None:
            on_epoch_end(epoch, metrics)
    if ema is not None:
        policy.load_state_dict(ema.module.state_dict())
    return policy.train(False)
