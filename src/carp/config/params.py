"""All of ``params.yaml`` as one validated object, and reading, flattening and writing it."""

from dataclasses import dataclass, field, replace
from typing import Any

from carp.config.checks import ConfigError, _require
from carp.config.data import DataConfig
from carp.config.evaluation import EvalConfig
from carp.config.experiments import ComparisonConfig, StudyConfig, SweepConfig, TrackingConfig
from carp.config.image_encoder import ImageEncoderConfig
from carp.config.serving import ServingConfig
from carp.config.tokenizer import TokenizerConfig
from carp.config.tokenizer_kinds import (
    BinningConfig,
    BSplineConfig,
    CarpMsvqConfig,
    FastConfig,
    FsqConfig,
    JointMsvqConfig,
    ResidualVqConfig,
    kind_section,
)
from carp.config.training import TrainingConfig
from carp.policies.sections import family_sections, teacher_of
from carp.tasks import TASK_NAMES, resolve_task
from carp.tasks.base import ActionFormat, Task

FAMILY_SECTIONS = "family_sections"
"""Marks the two `Params` fields whose YAML sections are named after the registered policy families."""


@dataclass(frozen=True)
class Params:
    """All of ``params.yaml``. ``scales`` and ``codebook_size`` are top-level so ``dvc exp run -S`` reaches them.

    Attributes:
        scales: ``s_k``, tokens per action dimension at each scale, coarse to fine; ``K`` is the number of scales and
            a chunk has ``L = A * sum(scales)`` tokens. Positive, strictly increasing integers, the last at most
            ``data.action_horizon``. The scales quantize a latent of length ``l = max(e, s_K)``, where ``e =
            data.action_horizon / 2**len(tokenizer.channel_mult)`` is the encoder's output length (4 by default): a
            last scale below ``e`` reconstructs from coarser maps only (``[1, 2, 3]``), one above it quantizes a
            latent resampled to its own length (``[1, 2, 3, 4, 5]``, as the paper's Fig. 10 does for K = 5 and 6).
        codebook_size: ``V``, codes per action dimension, which is also the policy's vocabulary per token; an integer
            >= 2 and at least ``inference.carp.top_k``.
        tasks: Tasks the pipeline runs, each at most once, all in one action space (one tokenizer serves them: the
            arms and Push-T do not mix); the per-task stages (``collect``, ``ingest``, ``train_policy``,
            ``evaluate``) fan out over this list. A registered task (``carp.tasks``: the robosuite arms lift, can,
            square, stack, nut_assembly, stack_three and threading, and pusht) is evaluated in its simulator. Any
            other name (lower-case letters, digits and ``_``) is a task without a simulator: its
            ``data.raw_files.<name>`` must name a LeRobotDataset folder, whose ``meta/info.json`` gives the actions
            and observations (``carp.tasks.offline``), and policies are evaluated offline, by their action error on
            the held-out episodes.
        policies: Policy families trained and evaluated on every task, each at most once, among the registered ones
            (``carp.policies.registry``); ``train_policy`` and ``evaluate`` fan out over tasks x policies. Each family
            has its own section named after it (its model and optimizer) and an ``inference.<family>`` section.
            Empty only when ``multitask`` lists a family: the run then trains multi-task policies alone, and its
            report compares them with single-task policies of other runs (``comparison.references``).
        seeds: Training seeds: every family is trained and evaluated once per seed on every task (``train_policy``
            and ``evaluate`` fan out over tasks x policies x seeds); integers >= 0, each at most once. The tokenizer
            stays one per pipeline.
        multitask: Policy families that also train one multi-task policy over all of ``tasks`` (each demo labelled
            with its task, a learned task embedding in the observation encoder, each task normalized with its own
            statistics), evaluated on every task beside the single-task policies; registered families, each at most
            once, not necessarily in ``policies``. Empty (the default) adds no stage. Needs at least two tasks with
            state observations and the same observation keys; a key narrower in one task than in another (Lift's
            ``object`` is 10 wide, Can's 14) is zero-padded to the widest inside the policy. The ``train_multitask``
            and ``evaluate_multitask`` stages fan out over multitask x seeds (x tasks).
        register: Policy families whose trained policies the pipeline registers in the MLflow Model Registry, each at
            most once and each also in ``policies``. The ``register_policy`` stage fans out over tasks x register x
            seeds: it registers the checkpoint that ``evaluate`` ran on the test seeds (``eval.selection``) as
            ``carp-policy-<task>-<family>``, tagged with its evaluation, and points ``tracking.policy_alias`` at it.
            Empty (the default) adds no stage.
        device: Where training runs: ``auto`` (CUDA when available, else the CPU), ``cpu`` or ``cuda``. Evaluation
            rollouts run on the CPU.
        data: Demonstrations, ingestion and the time convention.
        tokenizer: The action tokenizer: its kind, where it comes from, and CARP's kind's training.
        tokenizer_carp_msvq: ``carp_msvq``'s own section, empty (its settings are ``tokenizer``, ``scales`` and
            ``codebook_size``).
        tokenizer_binning: Settings of the ``binning`` kind.
        tokenizer_fast: Settings of the ``fast`` kind.
        tokenizer_bspline: Settings of the ``bspline`` kind.
        tokenizer_fsq: Settings of the ``fsq`` kind.
        tokenizer_joint_msvq: Settings of the ``joint_msvq`` kind.
        tokenizer_residual_vq: Settings of the ``residual_vq`` kind.
        training: The training loop shared by every policy family.
        eval: Simulated evaluation.
        tracking: MLflow tracking.
        sweep: The Optuna sweep.
        comparison: The report's comparison of families: equivalence margin and significance level.
        study: The paper's studies run as DVC experiments (``make study``).
        serving: How ``carp serve --params`` predicts for several robots.
        image_encoder: The camera encoder every family puts in front of its network with ``data.observations:
            image``; its cameras and image size are ``data.cameras`` and ``data.image_size``, which the section
            must not restate otherwise.
        families: Family -> its section (the top-level key named after the family), for every registered family;
            a missing section takes the family's defaults, a section of an unknown family is refused.
        inference: Family -> its inference settings (``inference.<family>``), read by evaluation only, so a change
            reruns evaluation and not training; a missing entry takes the family's defaults.
    """

    scales: tuple[int, ...] = (1, 2, 3, 4)
    codebook_size: int = 512
    tasks: tuple[str, ...] = ("lift",)
    policies: tuple[str, ...] = ("carp",)
    seeds: tuple[int, ...] = (0,)
    multitask: tuple[str, ...] = ()
    register: tuple[str, ...] = ()
    device: str = "auto"
    data: DataConfig = field(default_factory=DataConfig)
    tokenizer: TokenizerConfig = field(default_factory=TokenizerConfig)
    tokenizer_carp_msvq: CarpMsvqConfig = field(default_factory=CarpMsvqConfig)
    tokenizer_binning: BinningConfig = field(default_factory=BinningConfig)
    tokenizer_fast: FastConfig = field(default_factory=FastConfig)
    tokenizer_bspline: BSplineConfig = field(default_factory=BSplineConfig)
    tokenizer_fsq: FsqConfig = field(default_factory=FsqConfig)
    tokenizer_joint_msvq: JointMsvqConfig = field(default_factory=JointMsvqConfig)
    tokenizer_residual_vq: ResidualVqConfig = field(default_factory=ResidualVqConfig)
    training: TrainingConfig = field(default_factory=TrainingConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    sweep: SweepConfig = field(default_factory=SweepConfig)
    comparison: ComparisonConfig = field(default_factory=ComparisonConfig)
    study: StudyConfig = field(default_factory=StudyConfig)
    serving: ServingConfig = field(default_factory=ServingConfig)
    image_encoder: ImageEncoderConfig = field(default_factory=ImageEncoderConfig)
    families: dict[str, Any] = field(default_factory=dict, metadata={FAMILY_SECTIONS: True})
    inference: dict[str, Any] = field(default_factory=dict, metadata={FAMILY_SECTIONS: True})

    def __post_init__(self) -> None:
        _require(len(self.tasks) >= 1, "tasks", self.tasks, "must list at least one task")
        for task in self.tasks:
            _require(
                task in TASK_NAMES or task in self.data.raw_files,
                "tasks",
                list(self.tasks),
                f"'{task}' is not a registered task {list(TASK_NAMES)}, and data.raw_files.{task} names no "
                "LeRobotDataset folder for a task without a simulator",
            )
        _require(len(set(self.tasks)) == len(self.tasks), "tasks", self.tasks, "must not repeat a task")
        for task, path in self.data.raw_files.items():
            _require(
                task in TASK_NAMES or task in self.tasks,
                f"data.raw_files.{task}",
                path,
                f"'{task}' is not a registered task {list(TASK_NAMES)} nor listed in tasks={list(self.tasks)}",
            )
        known = family_sections()
        _require(
            len(self.policies) >= 1 or len(self.multitask) >= 1,
            "policies",
            list(self.policies),
            "must list at least one policy family (empty only when multitask lists one)",
        )
        for name in self.policies:
            _require(name in known, "policies", list(self.policies), f"every family must be one of {list(known)}")
        _require(len(set(self.policies)) == len(self.policies), "policies", self.policies, "must not repeat a family")
        _require(len(self.seeds) >= 1, "seeds", list(self.seeds), "must list at least one training seed")
        _require(all(seed >= 0 for seed in self.seeds), "seeds", list(self.seeds), "every seed must be >= 0")
        _require(len(set(self.seeds)) == len(self.seeds), "seeds", list(self.seeds), "must not repeat a seed")
        self._check_multitask(known)
        self._check_register(known)
        self._check_tokenizer_kind(known)
        # Families without a section in the file take their defaults, so every registered family has a config.
        object.__setattr__(self, "families", {name: self.families.get(name) or known[name][0]() for name in known})
        object.__setattr__(self, "inference", {name: self.inference.get(name) or known[name][1]() for name in known})
        for section in (*self.families.values(), *self.inference.values()):
            if hasattr(section, "check_with"):  # constraints across sections, e.g. CARP's top_k <= codebook_size
                section.check_with(self)
        _require(self.device in ("auto", "cpu", "cuda"), "device", self.device, "must be auto, cpu or cuda")
        self._bind_image_encoder()
        _require(self.codebook_size >= 2, "codebook_size", self.codebook_size, "must be >= 2")
        horizon = self.data.action_horizon
        checked = (
            ("scales", [self.scales]),
            ("sweep.scale_schedules", self.sweep.scale_schedules),
            ("study.scale_schedules", self.study.scale_schedules),
        )
        for key, schedules in checked:
            for schedule in schedules:
                _require(
                    len(schedule) >= 1
                    and all(size >= 1 for size in schedule)
                    and all(a < b for a, b in zip(schedule, schedule[1:]))
                    and schedule[-1] <= horizon,
                    key,
                    list(self.scales) if key == "scales" else [list(s) for s in schedules],
                    f"every schedule must be positive, strictly increasing and end at most at data.action_horizon = "
                    f"{horizon}",
                )
        self.encoder_length  # noqa: B018 (checks that the horizon divides into the encoder's levels)
        selected_kind = self.tokenizer_kind_config
        if hasattr(selected_kind, "check_horizon"):  # a kind whose tokens depend on the chunk's length
            selected_kind.check_horizon(horizon)
        _require(
            len(self.sweep.confirm_seeds) >= self.comparison.min_seeds,
            "sweep.confirm_seeds",
            list(self.sweep.confirm_seeds),
            f"must hold at least comparison.min_seeds = {self.comparison.min_seeds} seeds: a family verdict needs them",
        )
        # Collection may try up to 3 seeds per kept demo (see carp.data.collect); evaluation must never reuse them.
        collection_end = self.data.collection_seed + 3 * max(self.data.demos_for(task) for task in self.tasks)
        evaluation_end = self.eval.seed + self.eval.episodes
        _require(
            evaluation_end <= self.data.collection_seed or self.eval.seed >= collection_end,
            "eval.seed",
            self.eval.seed,
            f"evaluation seeds [{self.eval.seed}, {evaluation_end}) overlap the collection seeds "
            f"[{self.data.collection_seed}, {collection_end})",
        )
        validation_end = self.eval.validation_seed + self.eval.validation_episodes
        _require(
            self.eval.validation_episodes == 0
            or validation_end <= self.data.collection_seed
            or self.eval.validation_seed >= collection_end,
            "eval.validation_seed",
            self.eval.validation_seed,
            f"validation seeds [{self.eval.validation_seed}, {validation_end}) overlap the collection seeds "
            f"[{self.data.collection_seed}, {collection_end})",
        )
        for task in self.tokenizer.tasks:
            _require(
                task in self.tasks,
                "tokenizer.tasks",
                list(self.tokenizer.tasks),
                f"every tokenizer task must also be in tasks={list(self.tasks)} (its demos are ingested there)",
            )
        self._check_tasks_share_actions_and_observations()
        per_task = {
            "data.num_demos_per_task": self.data.num_demos_per_task,
            "training.epochs_per_task": self.training.epochs_per_task,
            "eval.max_steps": self.eval.max_steps,
        }
        for name, mapping in per_task.items():
            for task in mapping:
                self.require_known_task(f"{name}.{task}", task)
        for task in self.tasks:
            _require(
                self.data.subset_size <= self.data.demos_for(task) or task in self.data.raw_files,
                "data.subset_size",
                self.data.subset_size,
                f"must be <= the {self.data.demos_for(task)} demos collected for {task}",
            )

    def require_known_task(self, key: str, task: str) -> None:
        """Refuse a per-task setting for a task that is neither registered nor one of `tasks` (an offline one)."""
        _require(
            task in TASK_NAMES or task in self.tasks,
            key,
            task,
            f"task must be a registered one {list(TASK_NAMES)} or listed in tasks={list(self.tasks)}",
        )

    def _check_multitask(self, known: dict[str, Any]) -> None:
        """Multi-task families are registered and distinct, over two tasks or more of state observations."""
        families = list(self.multitask)
        for name in families:
            _require(name in known, "multitask", families, f"every family must be one of {list(known)}")
        _require(len(set(families)) == len(families), "multitask", families, "must not repeat a family")
        if not families:
            return
        for name in families:
            _require(
                teacher_of(name) is None,
                "multitask",
                families,
                f"{name} distils its {teacher_of(name)} teacher, which trains on one task only",
            )
        _require(
            len(self.tasks) >= 2,
            "multitask",
            families,
            f"a multi-task policy needs at least two tasks, tasks={list(self.tasks)}",
        )
        _require(
            self.data.observations == "state",
            "multitask",
            families,
            f"multi-task policies train on state observations, data.observations={self.data.observations!r}",
        )

    def _check_tokenizer_kind(self, known: dict[str, Any]) -> None:
        # A family's config class may name the tokenizer kinds it can predict (`TOKENIZER_KINDS`); CARP's next-scale
        # family needs the per-dimension multi-scale layout that only carp_msvq has.
        for name in dict.fromkeys((*self.policies, *self.multitask)):
            accepted = getattr(known[name][0], "TOKENIZER_KINDS", None)
            _require(
                accepted is None or self.tokenizer.kind in accepted,
                "tokenizer.kind",
                self.tokenizer.kind,
                f"the {name} family predicts {' or '.join(accepted or ())} tokens only; choose another kind or "
                f"another family (next_token takes any kind)",
            )

    def _check_register(self, known: dict[str, Any]) -> None:
        """Registered families are distinct families the pipeline trains (``policies``)."""
        families = list(self.register)
        for name in families:
            _require(name in known, "register", families, f"every family must be one of {list(known)}")
            _require(
                name in self.policies,
                "register",
                families,
                f"every family must also be in policies={list(self.policies)} (the pipeline registers what it trains)",
            )
        _require(len(set(families)) == len(families), "register", families, "must not repeat a family")

    def _check_tasks_share_actions_and_observations(self) -> None:
        """Every task must take ``data.controller`` and the observation kind, and all must share one action space."""
        spaces = {}
        for task in self.tasks:
            try:
                task_spec = self.task(task)
            except ValueError as error:
                path = self.data.raw_files.get(task)
                raise ConfigError(f"data.raw_files.{task}={path!r}: {error}") from None
            try:
                spaces[task] = task_spec.action_format(self.data.controller).space
            except ValueError as error:
                raise ConfigError(f"data.controller={self.data.controller!r}: {error}") from None
            _require(
                self.data.observations != "image" or task_spec.supports_cameras,
                "data.observations",
                self.data.observations,
                f"{task} has no camera observations; use state",
            )
        _require(
            len(set(spaces.values())) == 1,
            "tasks",
            list(self.tasks),
            f"tasks must share one action space (one tokenizer serves them all), got {spaces}",
        )

    def task(self, name: str) -> Task:
        """The task `name` of this run: a registered one, or one without a simulator from its ``data.raw_files``.

        A relative ``data.raw_files`` path is read from the current directory, the project root where every stage
        runs (`carp.tasks.resolve_task`).

        Raises:
            ValueError: a name that is neither (the validation turns it into a `ConfigError` naming the key).
        """
        return resolve_task(name, self.data.raw_files.get(name))

    @property
    def action_format(self) -> ActionFormat:
        """How the tasks' stored actions map to the policy's (the same for every task in ``tasks``)."""
        return self.task(self.tasks[0]).action_format(self.data.controller)

    def obs_keys_for(self, task: str) -> tuple[str, ...]:
        """Low-dim obs keys of `task` in the replay buffer: ``data.low_dim_keys``, or the task's fixed observation."""
        task_spec = self.task(task)
        return self.data.low_dim_keys if task_spec.configurable_obs_keys else task_spec.default_obs_keys

    def max_steps_for(self, task: str) -> int:
        """Step limit of one evaluation episode of `task`: its ``eval.max_steps`` entry, else the task's default."""
        return self.eval.max_steps.get(task, self.task(task).default_max_steps)

    def training_for_seed(self, seed: int) -> TrainingConfig:
        """The training settings of the run with training seed `seed` (one entry of `seeds`)."""
        return replace(self.training, seed=seed)

    def family_config(self, name: str) -> Any:
        """The params section of policy family `name` (its model and optimizer)."""
        return self.families[name]

    def inference_settings(self, name: str, task: str) -> dict[str, Any]:
        """Keyword arguments of family `name`'s `configure_inference` when evaluating `task`."""
        return self.inference[name].settings_for(task)

    @property
    def policy_image_encoder(self) -> ImageEncoderConfig | None:
        """The camera encoder the policies train with: ``image_encoder`` with image observations, else None."""
        return self.image_encoder if self.data.observations == "image" else None

    def _bind_image_encoder(self) -> None:
        """The encoder sees the images ingest stored: ``data.cameras`` at ``data.image_size``."""
        encoder, data, defaults = self.image_encoder, self.data, ImageEncoderConfig()
        for name, value in (("cameras", data.cameras), ("image_size", data.image_size)):
            written = getattr(encoder, name)
            _require(
                written in (getattr(defaults, name), value),
                f"image_encoder.{name}",
                list(written) if name == "cameras" else written,
                f"is data.{name}; set data.{name} instead",
            )
        if data.observations == "image":
            object.__setattr__(
                self, "image_encoder", replace(encoder, cameras=data.cameras, image_size=data.image_size)
            )

    @property
    def latent_length(self) -> int:
        """``l``, the latent the scales quantize: the encoder's length, or the last scale where that is longer."""
        return max(self.encoder_length, self.scales[-1])

    @property
    def encoder_length(self) -> int:
        """``H / 2**len(channel_mult)``, the tokenizer encoder's output length; raises if ``H`` is not divisible."""
        downsampling = 2 ** len(self.tokenizer.channel_mult)
        _require(
            self.data.action_horizon % downsampling == 0,
            "data.action_horizon",
            self.data.action_horizon,
            f"must be divisible by 2**len(tokenizer.channel_mult) = {downsampling}",
        )
        return self.data.action_horizon // downsampling

    @property
    def tokenizer_kind_config(self) -> Any:
        """The selected kind's section, ``tokenizer_<tokenizer.kind>`` (empty for ``carp_msvq``)."""
        return getattr(self, kind_section(self.tokenizer.kind))

    @property
    def tokenizer_tasks(self) -> tuple[str, ...]:
        """Tasks whose demos train the tokenizer (``tokenizer.tasks`` or, when empty, ``tasks``)."""
        return self.tokenizer.tasks or self.tasks

    @property
    def action_space(self) -> str:
        """Name of the action space, e.g. ``panda-abs10``; part of the registered tokenizer's name."""
        return self.action_format.space
