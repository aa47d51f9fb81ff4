"""Typed, validated configuration: ``params.yaml`` loads into frozen dataclasses, one per section.

Every problem is reported at load time as a :class:`ConfigError` whose message names the dotted key
(``policy.learning_rate``), the offending value and the constraint. Unknown keys are errors, so a typo in
``dvc exp run -S`` fails loudly instead of silently training with a default.

The library never reads ``params.yaml`` itself: the pipeline scripts call :func:`load_params` and pass the typed
sections to library functions.
"""

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ruamel.yaml import YAML, YAMLError

TASK_NAMES = ("lift", "can", "square")
CONTROLLERS = ("absolute", "delta")
ACTION_DIMS = {"absolute": 10, "delta": 7}
EVAL_BACKENDS = ("onnxruntime", "torch")
TRAINING_PRECISIONS = ("auto", "float32", "bfloat16")
REGISTRY_URI_PREFIX = "models:/"


class ConfigError(ValueError):
    """A params file that does not match the schema or breaks a constraint."""


def _require(condition: bool, key: str, value: Any, constraint: str) -> None:
    if not condition:
        raise ConfigError(f"{key}={value!r}: {constraint}")


@dataclass(frozen=True)
class DataConfig:
    """Demonstrations, ingestion and the time convention (DESIGN.md sections 1 and 2).

    Attributes:
        num_demos: successful scripted demos collected per task.
        num_demos_per_task: task -> demos overriding `num_demos` for that task's collection (Square gained most from
            more data: alone, 100 -> 200 demos took it from 62-68% to 88%).
        collection_seed: first seed of collection; episode i uses ``collection_seed + i`` (failures included).
        collection_max_steps: step limit of one scripted episode (failures are discarded).
        controller: ``absolute`` (default, 10-D actions with 6-D rotation) or ``delta`` (7-D, kept as-is).
        obs_keys: low-dim observation keys concatenated (in this order) into the policy's input.
        obs_steps: ``To``, observation steps fed to the policy.
        action_horizon: ``H``, actions predicted per call.
        action_steps: ``Ta``, actions executed per call.
        filter_key: optional robomimic ``mask/<filter_key>`` selecting the demos to ingest.
        valid_fraction: share of demos held out for validation metrics.
        raw_files: optional task -> path of a user's robomimic file, used instead of scripted collection.
    """

    num_demos: int = 100
    collection_seed: int = 0
    collection_max_steps: int = 500
    controller: str = "absolute"
    obs_keys: tuple[str, ...] = ("object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
    obs_steps: int = 2
    action_horizon: int = 16
    action_steps: int = 8
    filter_key: str | None = None
    valid_fraction: float = 0.1
    raw_files: dict[str, str] = field(default_factory=dict)
    num_demos_per_task: dict[str, int] = field(default_factory=dict)

    def demos_for(self, task: str) -> int:
        """Scripted demos collected for `task`: its `num_demos_per_task` entry, else `num_demos`."""
        return self.num_demos_per_task.get(task, self.num_demos)

    def __post_init__(self) -> None:
        _require(self.num_demos >= 1, "data.num_demos", self.num_demos, "must be at least 1")
        _require_per_task_minimum(self.num_demos_per_task, "data.num_demos_per_task", "must be at least 1")
        _require(self.collection_seed >= 0, "data.collection_seed", self.collection_seed, "must be >= 0")
        _require(self.collection_max_steps >= 1, "data.collection_max_steps", self.collection_max_steps, "must be >= 1")
        _require(self.controller in CONTROLLERS, "data.controller", self.controller, f"must be one of {CONTROLLERS}")
        _require(len(self.obs_keys) > 0, "data.obs_keys", self.obs_keys, "must name at least one key")
        _require(self.obs_steps >= 1, "data.obs_steps", self.obs_steps, "must be at least 1")
        _require(self.action_horizon >= 1, "data.action_horizon", self.action_horizon, "must be at least 1")
        _require(
            1 <= self.action_steps <= self.action_horizon - self.obs_steps + 1,
            "data.action_steps",
            self.action_steps,
            f"must be between 1 and action_horizon - obs_steps + 1 = {self.action_horizon - self.obs_steps + 1}",
        )
        _require(0.0 <= self.valid_fraction < 1.0, "data.valid_fraction", self.valid_fraction, "must be in [0, 1)")
        for task in self.raw_files:
            _require(task in TASK_NAMES, f"data.raw_files.{task}", task, f"task must be one of {TASK_NAMES}")

    @property
    def action_dim(self) -> int:
        """``A``: 10 for absolute actions (pos, rot6d, gripper), 7 for delta actions."""
        return ACTION_DIMS[self.controller]


@dataclass(frozen=True)
class TokenizerConfig:
    """The per-dimension multi-scale VQ-VAE (DESIGN.md section 3) and its training.

    Attributes:
        source: ``pipeline`` (train and register here) or a registry URI ``models:/<name>@<alias>``.
        tasks: tasks whose windows train the tokenizer, each normalized with its own statistics; empty means the
            pipeline's ``tasks``.
        registry_alias: alias set on the registered version.
    """

    source: str = "pipeline"
    tasks: tuple[str, ...] = ()
    latent_channels: int = 8
    base_channels: int = 2
    channel_mult: tuple[int, ...] = (2, 4)
    commitment_weight: float = 0.25
    epochs: int = 60
    batch_size: int = 64
    learning_rate: float = 1e-2
    weight_decay: float = 0.0
    checkpoint_every: int = 5
    seed: int = 0
    registry_alias: str = "default"

    def __post_init__(self) -> None:
        _require(
            self.source == "pipeline" or (self.source.startswith(REGISTRY_URI_PREFIX) and "@" in self.source),
            "tokenizer.source",
            self.source,
            "must be 'pipeline' or a registry URI 'models:/<name>@<alias>'",
        )
        for task in self.tasks:
            _require(task in TASK_NAMES, "tokenizer.tasks", self.tasks, f"tasks must be among {TASK_NAMES}")
        _require(self.latent_channels >= 1, "tokenizer.latent_channels", self.latent_channels, "must be >= 1")
        _require(self.base_channels >= 1, "tokenizer.base_channels", self.base_channels, "must be >= 1")
        _require(
            len(self.channel_mult) >= 1 and all(m >= 1 for m in self.channel_mult),
            "tokenizer.channel_mult",
            self.channel_mult,
            "must be a non-empty list of positive integers",
        )
        _require(self.commitment_weight >= 0, "tokenizer.commitment_weight", self.commitment_weight, "must be >= 0")
        _positive_training_fields(self, "tokenizer")
        _require(bool(self.registry_alias.strip()), "tokenizer.registry_alias", self.registry_alias, "must be set")
        _require(
            self.registry_alias.lower() != "latest" and not self.registry_alias[:1].isdigit(),
            "tokenizer.registry_alias",
            self.registry_alias,
            "'latest' and names starting with a digit are reserved by the MLflow registry",
        )


@dataclass(frozen=True)
class PolicyConfig:
    """The coarse-to-fine transformer (DESIGN.md section 5) and its training.

    Attributes:
        precision: matmul precision of training steps: `auto` trains with bfloat16 autocast where the hardware
            multiplies bfloat16 natively (CPUs with AMX or AVX512-BF16, CUDA GPUs that support it) and in float32
            elsewhere; `float32` or `bfloat16` force one. Weights, optimizer state, attention on CPU, the loss and
            inference stay float32 (see `carp.training.runtime.resolve_precision`).
        epochs_per_task: task -> policy epochs of that task's policy, overriding `epochs` (Square measured 34% at
            20 epochs and 68% at 35; Can 82% at 20 alone, 66% at 35 in a three-task run; see docs/measurements.md).
        top_k_per_task: task -> token choice of that task's evaluation, overriding `top_k` (in three-task run C, top-5
            draws lifted Can from 48% to 78% while Square did best greedy; see docs/measurements.md). Decoding only: a
            change reruns evaluation, not training.
    """

    depth: int = 8
    width: int = 64
    num_heads: int = 8
    mlp_ratio: float = 4.0
    dropout: float = 0.0
    epochs: int = 20
    batch_size: int = 64
    learning_rate: float = 1e-3
    weight_decay: float = 0.05
    warmup_steps: int = 100
    use_ema: bool = False
    ema_decay: float = 0.999
    top_k: int = 1
    checkpoint_every: int = 1
    seed: int = 0
    precision: str = "auto"
    epochs_per_task: dict[str, int] = field(default_factory=dict)
    top_k_per_task: dict[str, int] = field(default_factory=dict)

    def epochs_for(self, task: str) -> int:
        """Policy epochs of `task`: its `epochs_per_task` entry, else `epochs`."""
        return self.epochs_per_task.get(task, self.epochs)

    def top_k_for(self, task: str) -> int:
        """Token choice when evaluating `task`'s policy (1 = greedy): its `top_k_per_task` entry, else `top_k`."""
        return self.top_k_per_task.get(task, self.top_k)

    def __post_init__(self) -> None:
        _require(self.depth >= 1, "policy.depth", self.depth, "must be >= 1")
        _require(self.width >= 1, "policy.width", self.width, "must be >= 1")
        _require(self.num_heads >= 1, "policy.num_heads", self.num_heads, "must be >= 1")
        _require(
            self.width % self.num_heads == 0,
            "policy.num_heads",
            self.num_heads,
            f"must divide policy.width={self.width}",
        )
        _require(self.mlp_ratio > 0, "policy.mlp_ratio", self.mlp_ratio, "must be > 0")
        _require(0.0 <= self.dropout < 1.0, "policy.dropout", self.dropout, "must be in [0, 1)")
        _positive_training_fields(self, "policy")
        _require(self.warmup_steps >= 0, "policy.warmup_steps", self.warmup_steps, "must be >= 0")
        _require(0.0 < self.ema_decay < 1.0, "policy.ema_decay", self.ema_decay, "must be in (0, 1)")
        _require(self.top_k >= 1, "policy.top_k", self.top_k, "must be >= 1 (1 = greedy)")
        _require(
            self.precision in TRAINING_PRECISIONS,
            "policy.precision",
            self.precision,
            f"must be one of {TRAINING_PRECISIONS}",
        )
        _require_per_task_minimum(self.epochs_per_task, "policy.epochs_per_task", "must be >= 1")
        _require_per_task_minimum(self.top_k_per_task, "policy.top_k_per_task", "must be >= 1 (1 = greedy)")


def _require_per_task_minimum(mapping: dict[str, int], name: str, constraint: str) -> None:
    """Refuse a task -> integer override whose task is unknown or whose value is below 1."""
    for task, value in mapping.items():
        key = f"{name}.{task}"
        _require(task in TASK_NAMES, key, task, f"task must be one of {TASK_NAMES}")
        _require(value >= 1, key, value, constraint)


def _positive_training_fields(section: Any, name: str) -> None:
    _require(section.epochs >= 1, f"{name}.epochs", section.epochs, "must be >= 1")
    _require(section.batch_size >= 1, f"{name}.batch_size", section.batch_size, "must be >= 1")
    _require(section.learning_rate > 0, f"{name}.learning_rate", section.learning_rate, "must be > 0")
    _require(section.weight_decay >= 0, f"{name}.weight_decay", section.weight_decay, "must be >= 0")
    _require(section.checkpoint_every >= 1, f"{name}.checkpoint_every", section.checkpoint_every, "must be >= 1")


@dataclass(frozen=True)
class EvalConfig:
    """Simulated evaluation (DESIGN.md section 6).

    Attributes:
        seed: first evaluation seed; must stay disjoint from the collection seeds.
        workers: parallel env processes; 0 means one per CPU core.
        max_steps: task -> step limit of one episode.
        backend: `onnxruntime` runs greedy batch-1 inference as an exported ONNX graph (~3x faster per chunk, see
            `carp.evaluation.onnx_policy`); `torch` runs the PyTorch modules. Top-k sampling always uses torch.
    """

    episodes: int = 50
    seed: int = 100_000
    workers: int = 0
    max_steps: dict[str, int] = field(default_factory=lambda: {"lift": 400, "can": 400, "square": 400})
    video: bool = False
    video_episodes: int = 2
    backend: str = "onnxruntime"

    def __post_init__(self) -> None:
        _require(self.episodes >= 1, "eval.episodes", self.episodes, "must be >= 1")
        _require(self.seed >= 0, "eval.seed", self.seed, "must be >= 0")
        _require(self.workers >= 0, "eval.workers", self.workers, "must be >= 0 (0 = one per core)")
        for task, steps in self.max_steps.items():
            _require(task in TASK_NAMES, f"eval.max_steps.{task}", task, f"task must be one of {TASK_NAMES}")
            _require(steps >= 1, f"eval.max_steps.{task}", steps, "must be >= 1")
        _require(self.video_episodes >= 0, "eval.video_episodes", self.video_episodes, "must be >= 0")
        _require(self.backend in EVAL_BACKENDS, "eval.backend", self.backend, f"must be one of {EVAL_BACKENDS}")


@dataclass(frozen=True)
class TrackingConfig:
    """MLflow tracking. A relative SQLite path is resolved against the project root by the pipeline."""

    uri: str = "sqlite:///mlflow.db"
    experiment_prefix: str = "carp"

    def __post_init__(self) -> None:
        _require(bool(self.uri), "tracking.uri", self.uri, "must be set")
        _require(bool(self.experiment_prefix), "tracking.experiment_prefix", self.experiment_prefix, "must be set")


@dataclass(frozen=True)
class SweepConfig:
    """Optuna study over scale schedules and codebook sizes (outside the default DAG).

    Attributes:
        heartbeat_seconds: how often a running trial marks itself alive in the storage; a killed sweep's trial is
            retried once its heartbeat is two intervals old.
    """

    study_name: str = "carp-sweep"
    storage: str = "sqlite:///optuna.db"
    num_trials: int = 8
    scale_schedules: tuple[tuple[int, ...], ...] = ((4,), (1, 4), (1, 2, 4), (1, 2, 3, 4))
    codebook_sizes: tuple[int, ...] = (64, 256, 512)
    prune_factor: float = 2.0
    heartbeat_seconds: int = 10

    def __post_init__(self) -> None:
        _require(self.num_trials >= 1, "sweep.num_trials", self.num_trials, "must be >= 1")
        _require(len(self.scale_schedules) >= 1, "sweep.scale_schedules", self.scale_schedules, "must not be empty")
        for size in self.codebook_sizes:
            _require(size >= 2, "sweep.codebook_sizes", self.codebook_sizes, "every size must be >= 2")
        _require(self.prune_factor > 1.0, "sweep.prune_factor", self.prune_factor, "must be > 1")
        _require(self.heartbeat_seconds >= 1, "sweep.heartbeat_seconds", self.heartbeat_seconds, "must be >= 1")


@dataclass(frozen=True)
class Params:
    """All of ``params.yaml``. ``scales`` and ``codebook_size`` are top-level so ``dvc exp run -S`` reaches them."""

    scales: tuple[int, ...] = (1, 2, 3, 4)
    codebook_size: int = 512
    tasks: tuple[str, ...] = ("lift",)
    device: str = "auto"
    data: DataConfig = field(default_factory=DataConfig)
    tokenizer: TokenizerConfig = field(default_factory=TokenizerConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    sweep: SweepConfig = field(default_factory=SweepConfig)

    def __post_init__(self) -> None:
        _require(len(self.tasks) >= 1, "tasks", self.tasks, "must list at least one task")
        for task in self.tasks:
            _require(task in TASK_NAMES, "tasks", self.tasks, f"every task must be one of {TASK_NAMES}")
        _require(len(set(self.tasks)) == len(self.tasks), "tasks", self.tasks, "must not repeat a task")
        _require(self.device in ("auto", "cpu", "cuda"), "device", self.device, "must be auto, cpu or cuda")
        _require(self.codebook_size >= 2, "codebook_size", self.codebook_size, "must be >= 2")
        latent_length = self.latent_length
        _require(
            all(s >= 1 for s in self.scales) and all(a < b for a, b in zip(self.scales, self.scales[1:])),
            "scales",
            list(self.scales),
            "must be positive and strictly increasing",
        )
        _require(
            len(self.scales) >= 1 and self.scales[-1] == latent_length,
            "scales",
            list(self.scales),
            f"must end at the latent length l = action_horizon / 2**len(channel_mult) = {latent_length}",
        )
        for schedule in self.sweep.scale_schedules:
            _require(
                len(schedule) >= 1
                and schedule[-1] == latent_length
                and all(a < b for a, b in zip(schedule, schedule[1:])),
                "sweep.scale_schedules",
                [list(s) for s in self.sweep.scale_schedules],
                f"every schedule must be strictly increasing and end at l = {latent_length}",
            )
        for key, top_k in [("policy.top_k", self.policy.top_k)] + [
            (f"policy.top_k_per_task.{task}", k) for task, k in self.policy.top_k_per_task.items()
        ]:
            _require(top_k <= self.codebook_size, key, top_k, f"must be <= codebook_size = {self.codebook_size}")
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
        for task in self.tokenizer.tasks:
            _require(
                task in self.tasks,
                "tokenizer.tasks",
                list(self.tokenizer.tasks),
                f"every tokenizer task must also be in tasks={list(self.tasks)} (its demos are ingested there)",
            )
        for task in self.tasks:
            _require(task in self.eval.max_steps, "eval.max_steps", self.eval.max_steps, f"has no entry for '{task}'")

    @property
    def latent_length(self) -> int:
        """``l = H / 2**len(channel_mult)``; raises if ``H`` is not divisible."""
        downsampling = 2 ** len(self.tokenizer.channel_mult)
        _require(
            self.data.action_horizon % downsampling == 0,
            "data.action_horizon",
            self.data.action_horizon,
            f"must be divisible by 2**len(tokenizer.channel_mult) = {downsampling}",
        )
        return self.data.action_horizon // downsampling

    @property
    def tokenizer_tasks(self) -> tuple[str, ...]:
        """Tasks whose demos train the tokenizer (``tokenizer.tasks`` or, when empty, ``tasks``)."""
        return self.tokenizer.tasks or self.tasks

    @property
    def action_space(self) -> str:
        """Name of the action space, e.g. ``panda-abs10``; part of the registered tokenizer's name."""
        prefix = "abs" if self.data.controller == "absolute" else "delta"
        return f"panda-{prefix}{self.data.action_dim}"


def params_from_dict(raw: dict[str, Any]) -> Params:
    """Build validated :class:`Params` from a parsed YAML mapping.

    Raises:
        ConfigError: unknown key, wrong type or broken constraint; the message names the dotted key.
    """
    return _build(Params, raw, prefix="")


def load_params(path: Path | str = "params.yaml") -> Params:
    """Load and validate a params file.

    Raises:
        ConfigError: the file is missing, is not YAML, or does not validate (message names the file and key).
    """
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"{path}: params file not found")
    try:
        raw = _read_yaml(path.read_text()) or {}
    except YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML ({_yaml_problem(error)})") from None
    try:
        return params_from_dict(raw)
    except ConfigError as error:
        raise ConfigError(f"{path}: {error}") from None


def _read_yaml(text: str) -> Any:
    # DVC parses params.yaml with ruamel.yaml's YAML 1.2 safe loader. Reading it with the same loader makes every
    # value mean here what DVC hashed and `dvc exp run -S` wrote: `1e-3` is a float (PyYAML's YAML 1.1 reads a
    # string), `yes` is a string (YAML 1.1: true), and a repeated key is an error (PyYAML keeps the last one).
    return YAML(typ="safe").load(text)


def _yaml_problem(error: YAMLError) -> str:
    problem = getattr(error, "problem", None)
    mark = getattr(error, "problem_mark", None)
    if problem and mark is not None:
        return f"{problem} at line {mark.line + 1}, column {mark.column + 1}"
    return str(error).strip().splitlines()[0]


def params_to_dict(params: Params) -> dict[str, Any]:
    """Plain nested dict (lists instead of tuples) of validated params, e.g. for logging or checkpoints."""
    return _plain(dataclasses.asdict(params))


def flatten_params(params: Params) -> dict[str, str]:
    """Dotted-key view (``policy.depth`` -> ``"8"``) for MLflow params."""
    flat: dict[str, str] = {}

    def visit(prefix: str, value: Any) -> None:
        if isinstance(value, dict) and value:
            for key, inner in value.items():
                visit(f"{prefix}.{key}" if prefix else str(key), inner)
        else:
            flat[prefix] = str(value)

    visit("", params_to_dict(params))
    return flat


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {key: _plain(inner) for key, inner in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(inner) for inner in value]
    return value


def _build(cls: type, raw: Any, prefix: str) -> Any:
    section = prefix.rstrip(".") or "params"
    if not isinstance(raw, dict):
        raise ConfigError(f"{section}: expected a mapping, got {type(raw).__name__}")
    hints = typing.get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls)}
    for key in raw:
        if key not in known:
            raise ConfigError(f"{prefix}{key}: unknown key (known: {', '.join(sorted(known))})")
    values = {}
    for name, value in raw.items():
        hint = hints[name]
        key = f"{prefix}{name}"
        if dataclasses.is_dataclass(hint):
            values[name] = _build(hint, value if value is not None else {}, prefix=f"{key}.")
        else:
            values[name] = _coerce(value, hint, key)
    return cls(**values)


def _coerce(value: Any, hint: Any, key: str) -> Any:
    origin = typing.get_origin(hint)
    arguments = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in arguments:
            return None
        inner = [argument for argument in arguments if argument is not type(None)]
        return _coerce(value, inner[0], key)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}={value!r}: expected a list")
        element = arguments[0]
        return tuple(_coerce(item, element, key) for item in value)
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{key}={value!r}: expected a mapping")
        key_type, value_type = arguments
        return {
            _coerce(inner_key, key_type, key): _coerce(inner, value_type, f"{key}.{inner_key}")
            for inner_key, inner in value.items()
        }
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}={value!r}: expected true or false")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}={value!r}: expected an integer")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}={value!r}: expected a number")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}={value!r}: expected a string")
        return value
    raise ConfigError(f"{key}: unsupported type {hint}")
