"""The `training` section: the shared loop's length, batches, snapshots and seeds."""

from dataclasses import dataclass, field

from carp.config.checks import SET_BY_PIPELINE, TRAINING_PRECISIONS, _require
from carp.config.data import _require_per_task_minimum
from carp.policies.sections import family_sections


@dataclass(frozen=True)
class TrainingConfig:
    """The training loop every policy family shares (each family's own section holds its model and optimizer).

    Attributes:
        epochs: Passes over a task's training windows; an integer >= 1. ``epochs_per_task`` overrides it per task.
        batch_size: Windows per optimizer step; an integer >= 1.
        checkpoint_every: Epochs between resumable training states in ``checkpoints/``; an integer >= 1. The last
            epoch is always saved.
        seed: The training seed of one run (weight initialization and shuffling); not a key of ``params.yaml``: the
            pipeline trains once per entry of the top-level ``seeds`` and sets it from that entry.
        snapshot_every: Epochs between the policy snapshots that training keeps for evaluation to select from
            (``eval.selection``); an integer >= 0, where 0 keeps none. The final policy is always a candidate.
        snapshot_last: Also keep a snapshot of each of the last this many epochs; an integer >= 0.
        precision: Matmul precision of training steps: ``auto`` trains with bfloat16 autocast where the hardware
            multiplies bfloat16 natively (CPUs with AMX or AVX512-BF16, CUDA GPUs that support it) and in float32
            elsewhere; ``float32`` or ``bfloat16`` force one. Weights, optimizer state, attention on CPU, the loss
            and inference stay float32 (see ``carp.training.runtime.resolve_precision``).
        epochs_per_task: Task -> epochs of that task's policies, overriding ``epochs``; each an integer >= 1, tasks
            registered (``carp.tasks``) or listed in ``tasks``. DVC tracks the mapping as one parameter, so a change
            reruns every ``train_policy`` stage; a task whose settings did not change resumes from its finished
            training state.
        epochs_per_policy: Policy family -> its epochs on every task, overriding ``epochs`` and ``epochs_per_task``
            (families converge at different rates: Diffusion Policy's denoisers need several times CARP's epochs);
            each an integer >= 1, families among the registered ones. Tracked like ``epochs_per_task``.
        num_processes: Training processes, all on the machine that runs the stage; an integer >= 1, at most
            ``batch_size``. Above 1, ``train_policy`` starts itself again under ``torchrun`` (DistributedDataParallel:
            NCCL with one CUDA device per process, so at most the number of GPUs; gloo on the CPU, each process taking
            an equal share of the cores). ``batch_size`` stays the windows of one optimizer step, split between the
            processes, so the steps are one process's; rank 0 alone logs to MLflow and writes training states and
            outputs.
    """

    epochs: int = 20
    batch_size: int = 64
    checkpoint_every: int = 1
    seed: int = field(default=0, metadata={SET_BY_PIPELINE: True})
    precision: str = "auto"
    epochs_per_task: dict[str, int] = field(default_factory=dict)
    num_processes: int = 1
    epochs_per_policy: dict[str, int] = field(default_factory=dict)
    snapshot_every: int = 0
    snapshot_last: int = 0

    def snapshot_epochs(self, epochs: int) -> tuple[int, ...]:
        """The epochs (1-based, ascending) after which a run of `epochs` epochs keeps a policy snapshot."""
        kept = {epoch for epoch in range(1, epochs + 1) if self.snapshot_every and epoch % self.snapshot_every == 0}
        kept |= set(range(max(1, epochs - self.snapshot_last + 1), epochs + 1)) if self.snapshot_last else set()
        return tuple(sorted(kept))

    def epochs_for(self, task: str, policy: str) -> int:
        """Epochs of family `policy` on `task`: its `epochs_per_policy` entry, else the task's, else `epochs`."""
        if policy in self.epochs_per_policy:
            return self.epochs_per_policy[policy]
        return self.epochs_per_task.get(task, self.epochs)

    def __post_init__(self) -> None:
        _require(self.epochs >= 1, "training.epochs", self.epochs, "must be >= 1")
        _require(self.batch_size >= 1, "training.batch_size", self.batch_size, "must be >= 1")
        _require(self.checkpoint_every >= 1, "training.checkpoint_every", self.checkpoint_every, "must be >= 1")
        _require(
            self.precision in TRAINING_PRECISIONS,
            "training.precision",
            self.precision,
            f"must be one of {TRAINING_PRECISIONS}",
        )
        _require_per_task_minimum(self.epochs_per_task, "training.epochs_per_task", "must be >= 1")
        for policy, value in self.epochs_per_policy.items():
            key = f"training.epochs_per_policy.{policy}"
            _require(policy in family_sections(), key, policy, f"family must be one of {list(family_sections())}")
            _require(isinstance(value, int) and value >= 1, key, value, "must be an integer >= 1")
        _require(self.num_processes >= 1, "training.num_processes", self.num_processes, "must be >= 1")
        _require(self.snapshot_every >= 0, "training.snapshot_every", self.snapshot_every, "must be >= 0 (0 = none)")
        _require(self.snapshot_last >= 0, "training.snapshot_last", self.snapshot_last, "must be >= 0")
        _require(
            self.num_processes <= self.batch_size,
            "training.num_processes",
            self.num_processes,
            f"must be <= batch_size={self.batch_size} (each process trains on a share of every batch)",
        )
