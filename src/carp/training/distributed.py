"""Training on several processes of one machine, as `torchrun` starts them: process group, batch shares, gradients.

Every process holds the whole model and the whole training set. While a process group runs (`start_process_group`),
the shared loop (`carp.training.loop.train_with_loss`) gives each process a contiguous share of every batch of the
epoch's seeded permutation (`batch_share`). `training.batch_size` stays the global batch: each share's mean loss is
weighted by its size, and DistributedDataParallel averages the gradients over the processes, which gives the gradient
of the whole batch's mean loss. So N processes take the optimizer steps of one process, up to the order of floating-
point sums. Rank 0 alone reports epochs and writes training states; every process reads the same state to resume.

Randomness inside a loss (a diffusion policy's noise and steps, dropout) is drawn per process: with several processes
each one seeds its generator at every epoch from (seed, epoch, rank) (`seed_epoch`). The processes then draw different
noise, and a resumed run draws what the uninterrupted one drew without storing every process's generator state. Such
a loss has the distribution of a one-process run, not its draws.

Backends: NCCL between CUDA devices (the process of local rank i uses `cuda:<i>`), gloo on the CPU, where each
process takes an equal share of the cores. One machine only: the launcher (`run_processes`) starts `torchrun
--standalone`.
"""

import ctypes
import logging
import os
import signal
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import TypeVar

import torch
import torch.distributed as dist
from torch import nn
from torch.nn.parallel import DistributedDataParallel

logger = logging.getLogger(__name__)

T = TypeVar("T")

# Long enough for rank 0 to write a training state or run the held-out evaluation while the others wait; a process
# that died is noticed sooner by torchrun, which then stops the others.
COLLECTIVE_TIMEOUT = timedelta(minutes=30)
_PR_SET_PDEATHSIG = 1


class ProcessesFailed(RuntimeError):
    """A process started by :func:`run_processes` failed; the message is one line naming ranks and exit codes."""


@dataclass(frozen=True)
class Processes:
    """Where this process stands among the training processes.

    Attributes:
        rank: this process's index, 0 to `world_size - 1`; rank 0 reports and writes.
        world_size: number of training processes; 1 without a process group.
    """

    rank: int = 0
    world_size: int = 1

    @property
    def is_main(self) -> bool:
        """True on rank 0, the process that logs, reports epochs and writes files."""
        return self.rank == 0

    @property
    def is_distributed(self) -> bool:
        """True when several processes train together."""
        return self.world_size > 1


def current_processes() -> Processes:
    """This process's rank and the number of processes of the running process group; (0, 1) without one."""
    if dist.is_available() and dist.is_initialized():
        return Processes(dist.get_rank(), dist.get_world_size())
    return Processes()


def cpu_threads_per_process(world_size: int) -> int:
    """An equal share (at least one) of the cores this process may run on: the processes must not oversubscribe them."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return max(1, cores // world_size)


def start_process_group(
    rank: int, world_size: int, local_rank: int, address: str, port: int, device: torch.device
) -> torch.device:
    """Join the process group of `world_size` training processes; NCCL on CUDA, gloo on the CPU.

    Args:
        rank: this process's rank among all processes.
        world_size: number of processes.
        local_rank: this process's rank among those of its machine; on CUDA it picks the device `cuda:<local_rank>`.
        address: host of the rendezvous store (torchrun's `MASTER_ADDR`).
        port: its port (torchrun's `MASTER_PORT`).
        device: the training device; a CUDA device's index is replaced by `local_rank`.

    Returns:
        The device this process trains on.

    Raises:
        ValueError: a rank outside `[0, world_size)`, or fewer visible CUDA devices than processes on the machine.
    """
    if not 0 <= rank < world_size or not 0 <= local_rank < world_size:
        raise ValueError(f"rank {rank} (local rank {local_rank}) is not among {world_size} processes")
    if device.type == "cuda":
        visible = torch.cuda.device_count()
        if local_rank >= visible:
            raise ValueError(f"local process {local_rank} needs cuda:{local_rank}; {visible} CUDA devices are visible")
        device = torch.device("cuda", local_rank)
        torch.cuda.set_device(device)
        backend, device_id = "nccl", device  # NCCL binds its communicator to the device (and barriers to it)
    else:
        torch.set_num_threads(cpu_threads_per_process(world_size))
        backend, device_id = "gloo", None
    dist.init_process_group(
        backend,
        init_method=f"tcp://{address}:{port}",
        rank=rank,
        world_size=world_size,
        timeout=COLLECTIVE_TIMEOUT,
        device_id=device_id,
    )
    logger.info("process %d of %d joined the %s process group on %s", rank, world_size, backend, device)
    return device


def stop_process_group() -> None:
    """Leave the process group, if any."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def end_with_launcher() -> None:
    """Have Linux kill this process when the launcher that started it dies.

    torchrun starts every process in a process group of its own (setsid), so killing the launcher's group (what
    stopping a DVC stage does) would otherwise leave them training and writing training states that a rerun would
    race with.
    Elsewhere than on Linux this does nothing.
    """
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        prctl = libc.prctl
    except (OSError, AttributeError):
        return
    prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)


def run_processes(script: Path, arguments: Sequence[str], num_processes: int) -> None:
    """Run `python script *arguments` as `num_processes` processes of one machine under torchrun, and wait.

    torchrun gives each process `RANK`, `LOCAL_RANK`, `WORLD_SIZE`, `MASTER_ADDR` and `MASTER_PORT` (a free port);
    when one process fails it stops the others.

    Raises:
        ProcessesFailed: a process exited with an error (its own output says why).
    """
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
    from torch.distributed.run import parse_args, run

    launch = parse_args(["--standalone", f"--nproc-per-node={num_processes}", str(script), *map(str, arguments)])
    try:
        run(launch)
    except ChildFailedError as error:
        exit_codes = {rank: failure.exitcode for rank, failure in error.failures.items()}
        raise ProcessesFailed(
            f"{script.name} on {num_processes} processes failed ({describe_failures(exit_codes)})"
        ) from None


def describe_failures(exit_codes: dict[int, int]) -> str:
    """The ranks that failed of their own accord, with exit codes, e.g. `rank 1 exit code 3`.

    When one process fails torchrun stops the others with SIGTERM, and whether a survivor had already finished by then
    is a race; those stopped ranks are not the cause and are left out, unless every rank was stopped (the launcher
    itself was told to stop).
    """
    stopped_by_launcher = -signal.SIGTERM
    causes = {rank: code for rank, code in exit_codes.items() if code != stopped_by_launcher} or exit_codes
    return ", ".join(f"rank {rank} exit code {code}" for rank, code in sorted(causes.items()))


def main_process_first(action: Callable[[], T], processes: Processes) -> T:
    """`action()` on rank 0, then on the other processes: rank 0 may tidy or delete files the others then read.

    With one process it is just `action()`.
    """
    if not processes.is_distributed:
        return action()
    if processes.is_main:
        result = action()
    dist.barrier()
    if not processes.is_main:
        result = action()
    return result


def require_same(value: int, what: str, processes: Processes) -> None:
    """Raise RuntimeError unless every process holds the same integer `value` (e.g. the epoch it resumes at)."""
    if not processes.is_distributed:
        return
    device = torch.device("cuda", torch.cuda.current_device()) if dist.get_backend() == "nccl" else None
    extremes = torch.tensor([value, -value], dtype=torch.long, device=device)
    dist.all_reduce(extremes, op=dist.ReduceOp.MAX)
    if int(extremes[0]) != -int(extremes[1]):
        raise RuntimeError(f"the training processes disagree on the {what}: from {-int(extremes[1])} to {extremes[0]}")


def value_of_main(value: int, processes: Processes) -> int:
    """Rank 0's integer `value` on every process (a choice each process could make differently, made once)."""
    if not processes.is_distributed:
        return value
    device = torch.device("cuda", torch.cuda.current_device()) if dist.get_backend() == "nccl" else None
    shared = torch.tensor([value], dtype=torch.long, device=device)
    dist.broadcast(shared, src=0)
    return int(shared[0])


def seed_epoch(seed: int, epoch: int, processes: Processes) -> None:
    """With several processes, seed torch's generators from (seed, epoch, rank) (see the module docstring)."""
    if processes.is_distributed:
        torch.manual_seed(((seed * 1_000_003 + epoch) * 65_537 + processes.rank) % 2**63)


def batch_share(indices: torch.Tensor, processes: Processes) -> tuple[torch.Tensor, float]:
    """This process's share of a global batch and the weight of its mean loss.

    The shares are contiguous and differ in size by at most one window. Weighting a share's mean loss by
    `share_size * world_size / batch_size` makes the processes' average the mean loss of the whole batch, also for
    the last, smaller batch of an epoch.

    Args:
        indices: (b,) window indices of the global batch, the same on every process.
        processes: this process's rank and the number of processes.

    Returns:
        The share's indices (b_r,) and its loss weight (1.0 for one process). A batch of fewer windows than
        processes leaves some without any: they take the first window with weight 0, so that they still take part
        in the gradient all-reduce.
    """
    if not processes.is_distributed:
        return indices, 1.0
    share = indices.tensor_split(processes.world_size)[processes.rank]
    if share.numel() == 0:
        return indices[:1], 0.0
    return share, share.numel() * processes.world_size / indices.numel()


def mean_over_processes(weighted_loss: torch.Tensor, processes: Processes) -> float:
    """The global batch's mean loss from each process's weighted share loss (scalar); the same on every process."""
    if not processes.is_distributed:
        return float(weighted_loss)
    total = weighted_loss.detach().float().reshape(1).clone()
    dist.all_reduce(total)
    return float(total) / processes.world_size


def sums_over_processes(sums: dict[str, torch.Tensor], processes: Processes) -> dict[str, float]:
    """Each scalar of `sums` (this process's share) added over the processes; the same on every process."""
    if not processes.is_distributed or not sums:
        return {name: float(value) for name, value in sums.items()}
    names = sorted(sums)  # the same order on every process
    totals = torch.stack([torch.as_tensor(sums[name], dtype=torch.float64).reshape(()) for name in names])
    dist.all_reduce(totals)
    return {name: float(total) for name, total in zip(names, totals.tolist(), strict=True)}


class _TrainingStep(nn.Module):
    """A family's training step as the `forward` of a module, the call DistributedDataParallel wraps."""

    def __init__(self, policy: nn.Module, step: Callable) -> None:
        super().__init__()
        self.policy = policy
        self.step = step

    def forward(self, batch: dict[str, torch.Tensor]):
        return self.step(batch)


def step_function(policy: nn.Module, step: Callable[[dict], T], processes: Processes) -> Callable[[dict], T]:
    """The family's training `step` of `policy`, with its gradients averaged over the processes when there are several.

    The families compute their loss in a method or function that calls their submodules directly, not in `forward`,
    so DistributedDataParallel wraps a small module whose `forward` is that step. DDP hooks the gradients of the
    parameters themselves, so every trained parameter the loss reaches is all-reduced wherever the step calls it, in
    buckets while the backward pass still runs (a hand-written all-reduce after `backward` could not overlap). Frozen
    parameters (a tokenizer) take no part. The buffers are constant tables and masks, equal on every process from
    construction, so they are not broadcast at every step.

    Args:
        policy: the policy being trained (an `nn.Module`), on this process's device; identical on every process.
        step: maps a batch to the loss of this process's share (with any metric sums, `carp.training.loop`).
        processes: this process's rank and the number of processes.

    Returns:
        `step` itself with one process, else the DDP-wrapped step.
    """
    if not processes.is_distributed:
        return step
    device = next(policy.parameters()).device
    return DistributedDataParallel(
        _TrainingStep(policy, step), device_ids=[device] if device.type == "cuda" else None, forward_sync_buffers=False
    )
