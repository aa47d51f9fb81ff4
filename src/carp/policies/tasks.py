"""The tasks a multi-task policy was trained on: their names, the task embedding's width, each task's statistics.

CARP's multi-task setting (the paper's supplementary section H) trains one policy over several tasks and conditions it
on a learnable task embedding (3-D there) concatenated with the observations of every step. Here the embedding lives
in the shared observation encoder (`carp.policies.observations.TaskConditionedObservations`), so every family is
multi-task capable without knowing it.

Each task keeps its own min-max statistics, as the shared tokenizer saw every task's actions normalized with their
own (`carp.tokenizer.artifact`): training normalizes every task's windows with its task's, and a policy evaluated on
a task un-normalizes with that task's (:meth:`PolicyTasks.index` refuses a task the policy was not trained on). The
policy's own `obs_normalizer` and `action_normalizer` are those of its *selected* task
(`carp.policies.wrapper.PolicyModule.select_task`), whose index is also the default task of a prediction.

Tasks whose obs keys differ in width (Lift's `object` against Can's) share a padded layout
(`carp.data.obs_padding`): the policy takes each task's own observations and pads them itself, so its obs statistics
are all in the padded layout, and :meth:`PolicyTasks.padding` tells how the selected task's features sit in it.

The record is plain values stored in the policy's metadata under :data:`TASKS_METADATA_KEY`, so it travels in every
family's checkpoint unchanged; a single-task policy has no such entry and no task embedding.
"""

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from carp.data.normalizer import MinMaxNormalizer
from carp.data.obs_padding import ObservationPadding, padded_layout

TASKS_METADATA_KEY = "tasks"
"""Metadata entry of a multi-task policy: :meth:`PolicyTasks.to_dict`."""

DEFAULT_TASK_EMBEDDING_DIM = 3
"""Width of the learned task embedding (the paper's 3-D embedding)."""


@dataclass(frozen=True)
class PolicyTasks:
    """Tasks of a multi-task policy, in task-index order.

    Attributes:
        names: task names; index i is task id i. At least two, no repeats.
        embedding_dim: width of the learned task embedding appended to every observation step's features; >= 1.
        obs_normalizers: task -> its observation statistics in the padded layout, `Do` wide.
        action_normalizers: task -> its `A` action statistics.
        selected: the task whose statistics the policy currently uses; one of `names`.
        obs_widths: task -> its own features per obs key, whose per-key maxima are the padded layout; None when every
            task has the padded layout itself (no padding; policies trained before padding existed record none).
    """

    names: tuple[str, ...]
    obs_normalizers: Mapping[str, MinMaxNormalizer]
    action_normalizers: Mapping[str, MinMaxNormalizer]
    embedding_dim: int = DEFAULT_TASK_EMBEDDING_DIM
    selected: str | None = None
    obs_widths: Mapping[str, tuple[int, ...]] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "names", tuple(self.names))
        if len(self.names) < 2 or len(set(self.names)) != len(self.names):
            raise ValueError(f"a multi-task policy needs at least two distinct tasks, got {list(self.names)}")
        if isinstance(self.embedding_dim, bool) or not isinstance(self.embedding_dim, int) or self.embedding_dim < 1:
            raise ValueError(f"task embedding_dim must be a positive integer, got {self.embedding_dim!r}")
        for what, normalizers in (("obs", self.obs_normalizers), ("action", self.action_normalizers)):
            if set(normalizers) != set(self.names):
                raise ValueError(f"{what} statistics are for tasks {sorted(normalizers)}, not {list(self.names)}")
            widths = {task: normalizer.num_features for task, normalizer in normalizers.items()}
            if len(set(widths.values())) != 1:
                raise ValueError(f"{what} statistics of the tasks differ in width: {widths}")
        if self.selected is None:
            object.__setattr__(self, "selected", self.names[0])
        self.index(self.selected)
        if self.obs_widths is not None:
            if set(self.obs_widths) != set(self.names):
                raise ValueError(f"obs widths are for tasks {sorted(self.obs_widths)}, not {list(self.names)}")
            widths = {task: tuple(int(width) for width in self.obs_widths[task]) for task in self.names}
            object.__setattr__(self, "obs_widths", widths)
            # Kept: the selected task's padding is looked up on every prediction.
            object.__setattr__(self, "_paddings", padded_layout(widths))
            padded_dim = self._paddings[self.names[0]].output_dim
            obs_dim = self.obs_normalizers[self.names[0]].num_features
            if padded_dim != obs_dim:
                raise ValueError(f"obs widths {widths} pad to {padded_dim} features, the obs statistics have {obs_dim}")

    @property
    def num_tasks(self) -> int:
        """Number of task indices."""
        return len(self.names)

    def index(self, task: str) -> int:
        """The task id of `task`.

        Raises:
            ValueError: the policy was not trained on `task`; the message lists the tasks it was trained on.
        """
        if task not in self.names:
            raise ValueError(f"this policy was trained on tasks {list(self.names)}, not on {task!r}")
        return self.names.index(task)

    def with_selected(self, task: str) -> "PolicyTasks":
        """The same tasks with `task` selected (ValueError if the policy was not trained on it)."""
        self.index(task)
        return PolicyTasks(
            self.names, self.obs_normalizers, self.action_normalizers, self.embedding_dim, task, self.obs_widths
        )

    def padding(self, task: str | None = None) -> ObservationPadding | None:
        """How `task`'s (default: the selected task's) own observations are padded; None when no task is padded."""
        if self.obs_widths is None:
            return None
        return self._paddings[self.selected if task is None else task]

    def to_dict(self) -> dict[str, Any]:
        """Plain-types view, as the metadata stores it."""
        return {
            "names": list(self.names),
            "embedding_dim": self.embedding_dim,
            "selected": self.selected,
            "obs_widths": None if self.obs_widths is None else {task: list(w) for task, w in self.obs_widths.items()},
            "normalizers": {
                task: {"obs": self.obs_normalizers[task].to_dict(), "action": self.action_normalizers[task].to_dict()}
                for task in self.names
            },
        }

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "PolicyTasks":
        """Inverse of :meth:`to_dict`."""
        normalizers = values["normalizers"]
        return cls(
            names=tuple(values["names"]),
            obs_normalizers={task: MinMaxNormalizer.from_dict(entry["obs"]) for task, entry in normalizers.items()},
            action_normalizers={
                task: MinMaxNormalizer.from_dict(entry["action"]) for task, entry in normalizers.items()
            },
            embedding_dim=int(values["embedding_dim"]),
            selected=values.get("selected"),
            obs_widths=values.get("obs_widths"),
        )


def metadata_tasks(metadata: Mapping[str, Any] | None) -> PolicyTasks | None:
    """The tasks a policy's metadata records, or None for a single-task policy."""
    entry = (metadata or {}).get(TASKS_METADATA_KEY)
    return None if entry is None else PolicyTasks.from_dict(entry)
