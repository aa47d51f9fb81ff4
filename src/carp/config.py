"""Typed, validated configuration: ``params.yaml`` loads into frozen dataclasses, one per section.

Every problem is reported at load time as a :class:`ConfigError` whose message names the dotted key
(``carp.learning_rate``), the offending value and the constraint. Unknown keys are errors, so a typo in
``dvc exp run -S`` fails loudly instead of silently training with a default.

The library never reads ``params.yaml`` itself: the pipeline scripts call :func:`load_params` and pass the typed
sections to library functions.
"""

import dataclasses
import re
import types
import typing
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar

from ruamel.yaml import YAML, YAMLError

from carp.tasks import TASK_NAMES, get_task
from carp.tasks.base import ActionFormat

CONTROLLERS = ("absolute", "delta")
EVAL_BACKENDS = ("onnxruntime", "torch")
TRAINING_PRECISIONS = ("auto", "float32", "bfloat16")
OBSERVATION_KINDS = ("state", "image")
SELECTION_RULES = ("final", "best_validation", "lowest_loss", "average_last")
SWEEP_PRUNERS = ("successive_halving", "hyperband", "none")
SET_BY_PIPELINE = "set_by_pipeline"
"""Field metadata of a setting that the pipeline derives for each run and that ``params.yaml`` must not hold."""
REGISTRY_URI_PREFIX = "models:/"
# robomimic names a camera's images obs/<camera>_image (as carp.data.robomimic_schema does).
IMAGE_KEY_SUFFIX = "_image"


class ConfigError(ValueError):
    """A params file that does not match the schema or breaks a constraint."""


def _require(condition: bool, key: str, value: Any, constraint: str) -> None:
    if not condition:
        raise ConfigError(f"{key}={value!r}: {constraint}")


def require_registry_alias(key: str, alias: Any) -> None:
    """Refuse at `key` an alias the MLflow registry would refuse or reserve (the one rule for every alias carp sets).

    An alias is letters, digits, ``_`` and ``-`` (MLflow's characters), not ``latest`` in any case (MLflow's moving
    pointer), not ``v<digits>`` (MLflow's version aliases) and not starting with a digit (a version number).
    """
    _require(isinstance(alias, str) and bool(alias), key, alias, "must be set")
    _require(
        re.fullmatch(r"[\w-]+", alias) is not None,
        key,
        alias,
        "may only contain letters, digits, '_' and '-' (the MLflow registry's alias characters)",
    )
    _require(
        alias.lower() != "latest" and not alias[:1].isdigit() and re.fullmatch(r"[vV]\d+", alias) is None,
        key,
        alias,
        "'latest', 'v<digits>' and names starting with a digit are reserved by the MLflow registry",
    )


def require_positive_int(key: str, value: Any) -> None:
    """Refuse anything but an integer >= 1 at `key` (a bool or a whole float such as 8.0 included)."""
    _require(
        isinstance(value, int) and not isinstance(value, bool) and value >= 1, key, value, "must be an integer >= 1"
    )


def require_optimizer_settings(section: str, config: Any) -> None:
    """Check the optimizer fields every policy family's section has, naming them under `section`.

    Args:
        section: the params section, e.g. `carp` or `diffusion_unet`.
        config: a family config with `learning_rate`, `weight_decay`, `warmup_steps` and `use_ema`.
    """
    _require(config.learning_rate > 0, f"{section}.learning_rate", config.learning_rate, "must be > 0")
    _require(config.weight_decay >= 0, f"{section}.weight_decay", config.weight_decay, "must be >= 0")
    _require(
        isinstance(config.warmup_steps, int) and not isinstance(config.warmup_steps, bool) and config.warmup_steps >= 0,
        f"{section}.warmup_steps",
        config.warmup_steps,
        "must be an integer >= 0",
    )
    _require(isinstance(config.use_ema, bool), f"{section}.use_ema", config.use_ema, "must be true or false")


@dataclass(frozen=True)
class DataConfig:
    """Demonstrations, ingestion and the time convention (docs/architecture.md, "Data path" and "Time convention").

    Attributes:
        num_demos: Successful scripted demos collected per task; an integer >= 1. Collection may try up to 3 seeds per
            kept demo, so the collection seeds ``[collection_seed, collection_seed + 3 * demos)`` must stay clear of
            the evaluation seeds (see ``eval.seed``).
        collection_seed: First seed of scripted collection; an integer >= 0. Attempt i uses ``collection_seed + i``,
            failed attempts included.
        collection_max_steps: Step limit of one scripted episode, in the task's control steps (20 Hz for the arms,
            10 Hz for Push-T); an integer >= 1, capped at a task's own limit (Push-T: 300). An attempt that has not
            succeeded by then is discarded.
        controller: ``absolute`` or ``delta``. For the arm tasks, with ``absolute`` the operational-space controller
            takes absolute poses and actions are stored 10-D (position, 6-D rotation, gripper), so A = 10; with
            ``delta`` it takes pose deltas and actions stay 7-D (A = 7). Push-T takes ``absolute`` only (the agent's
            2-D target, A = 2). Part of the registered tokenizer's name (``panda-abs10``, ``pusht-abs2``).
        obs_keys: The arm tasks' low-dim observation keys of the robomimic file (``obs/<key>``), concatenated in this
            order into the policy's input; at least one, and each must exist in the file (checked when the data is
            ingested). Push-T has one fixed observation (``block_keypoints``, ``agent_pos``) and ignores them.
        obs_steps: ``To``, observation steps the policy sees per decision; an integer >= 1.
        action_horizon: ``H``, actions predicted per decision, in control steps; an integer >= 1. Must be divisible by
            ``2**len(tokenizer.channel_mult)`` (each encoder level halves the length), and at least the last entry of
            ``scales`` (a scale has at most one token per action step).
        action_steps: ``Ta``, actions executed per decision before the policy is asked again; an integer between 1
            and ``action_horizon - obs_steps + 1``.
        filter_key: Optional robomimic filter key: only the demos listed in the file's ``mask/<filter_key>`` are
            ingested; null ingests every demo.
        valid_fraction: Share of each task's demos held out for validation metrics when the file has no
            ``mask/valid`` (that mask wins when present); a number in [0, 1).
        raw_files: Task -> path of your own robomimic-schema HDF5 file (relative to the project root), validated and
            used instead of scripted collection; tasks among the registered ones (``carp.tasks``). Its ``env_args``
            must name the task's env and its actions the task's width (7 for the arms, 2 for Push-T).
        num_demos_per_task: Task -> scripted demos for that task, overriding ``num_demos``; each an integer >= 1, tasks
            among the registered ones (``carp.tasks``). DVC tracks the whole mapping: changing one entry reruns every
            ``collect`` stage, but collection is deterministic, so only that task's data and what depends on it change.
        observations: What the policy observes: ``state`` (the low-dim ``obs_keys``, object pose included) or
            ``image`` (camera images of ``cameras`` plus the proprioception of ``proprioception_keys``, no object
            pose). Only the ingest stage tracks the image settings; in a ``state`` run, changing one reruns ingest
            alone, whose output is then unchanged, so nothing downstream reruns.
        cameras: robosuite cameras whose images are ingested with ``observations: image``, each giving the obs key
            ``<camera>_image``; at least one, no repeats. Taken from the robomimic file when it stores that key,
            otherwise rendered from the demos' stored simulator states.
        image_size: Height and width of the camera images in pixels (robomimic's image datasets: 84); an integer
            >= 1. Images a file stores must already have this size.
        render_workers: Processes rendering camera images in ingest, each with its own simulator; an integer >= 0,
            0 meaning one per CPU core. The rendered images do not depend on it, so DVC does not track it.
        proprioception_keys: Low-dim observation keys ingested with the images (``observations: image``),
            concatenated in this order; at least one, none of them a camera image. The default is the robot's own
            state (end-effector position and quaternion, gripper joints), without the object's privileged pose.
        subset_size: Demos of each task's file that ingest keeps, for data-efficiency studies; an integer >= 0, 0
            keeping every demo, otherwise at most the demos the file holds. The kept demos are the first
            ``subset_size`` of one seeded shuffle of the file's demos (``carp.data.subsets``): with the same file and
            ``subset_seed`` a smaller subset is part of every larger one, and every family trains on the same demos.
        subset_seed: Seed of that shuffle; an integer >= 0.
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
    observations: str = "state"
    cameras: tuple[str, ...] = ("agentview", "robot0_eye_in_hand")
    image_size: int = 84
    render_workers: int = 0
    proprioception_keys: tuple[str, ...] = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
    subset_size: int = 0
    subset_seed: int = 0

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
        _require(
            self.observations in OBSERVATION_KINDS,
            "data.observations",
            self.observations,
            f"must be one of {OBSERVATION_KINDS}",
        )
        cameras = list(self.cameras)
        _require(len(cameras) > 0, "data.cameras", cameras, "must name at least one camera")
        _require(all(camera for camera in cameras), "data.cameras", cameras, "camera names must not be empty")
        _require(len(set(cameras)) == len(cameras), "data.cameras", cameras, "must name each camera once")
        require_positive_int("data.image_size", self.image_size)
        _require(
            isinstance(self.render_workers, int)
            and not isinstance(self.render_workers, bool)
            and self.render_workers >= 0,
            "data.render_workers",
            self.render_workers,
            "must be an integer >= 0 (0 = one per CPU core)",
        )
        keys = list(self.proprioception_keys)
        _require(len(keys) > 0, "data.proprioception_keys", keys, "must name at least one key")
        _require(len(set(keys)) == len(keys), "data.proprioception_keys", keys, "must name each key once")
        images = [key for key in keys if key.endswith(IMAGE_KEY_SUFFIX)]
        _require(not images, "data.proprioception_keys", keys, f"must be low-dim keys, not camera images {images}")
        _require(self.subset_size >= 0, "data.subset_size", self.subset_size, "must be >= 0 (0 = every demo)")
        _require(self.subset_seed >= 0, "data.subset_seed", self.subset_seed, "must be >= 0")

    @property
    def image_keys(self) -> tuple[str, ...]:
        """Obs keys of the camera images (``<camera>_image``, in ``cameras`` order) with ``observations: image``."""
        return tuple(f"{camera}{IMAGE_KEY_SUFFIX}" for camera in self.cameras) if self.observations == "image" else ()

    @property
    def low_dim_keys(self) -> tuple[str, ...]:
        """Low-dim obs keys stored in the replay buffer: ``obs_keys`` for state, ``proprioception_keys`` for image."""
        return self.proprioception_keys if self.observations == "image" else self.obs_keys


@dataclass(frozen=True)
class TokenizerConfig:
    """The per-dimension multi-scale VQ-VAE (docs/architecture.md, "Action tokenizer") and its training.

    Attributes:
        source: Where the tokenizer comes from: ``pipeline`` trains it here and registers it in the MLflow Model
            Registry; a registry URI ``models:/<name>@<alias>`` fetches that registered version instead, whose action
            space, ``scales`` and ``codebook_size`` must match these params.
        tasks: Tasks whose demo windows train the tokenizer, each normalized with its own min-max statistics; empty
            means the pipeline's ``tasks``. Every entry must also be in ``tasks`` (its demos are ingested there).
        latent_channels: ``C``, latent channels per action dimension, which is also the width of a code; an integer
            >= 1.
        base_channels: Channels per action dimension of the encoder's first convolution; an integer >= 1. Level i of
            the encoder has ``base_channels * channel_mult[i]`` channels per dimension.
        channel_mult: Channel multiplier of each encoder level (the decoder mirrors it); a non-empty list of positive
            integers. Each level halves the time length, so the encoder's output is ``action_horizon /
            2**len(channel_mult)`` steps long; ``scales`` may end below or above that length (the latent length ``l``
            in docs/architecture.md, "Symbols").
        commitment_weight: Weight of the commitment loss that pulls encoder latents towards their quantized values,
            relative to the reconstruction loss; a number >= 0.
        epochs: Passes over the training windows; an integer >= 1.
        batch_size: Windows per optimizer step; an integer >= 1.
        learning_rate: Peak AdamW learning rate, reached after a linear warm-up and followed by a cosine decay to 5% of
            the peak; a number > 0.
        weight_decay: AdamW weight decay of the convolution weights (biases, norms and the codebook are not decayed);
            a number >= 0.
        checkpoint_every: Epochs between resumable training states in ``checkpoints/``; an integer >= 1. The last
            epoch is always saved.
        seed: Seeds weight initialization, shuffling, augmentation and code restarts; any integer.
        registry_alias: Alias the ``register_tokenizer`` stage sets on the registered version: letters, digits,
            ``_`` and ``-``, not ``latest``, not ``v<digits>`` and not starting with a digit (reserved by the MLflow
            registry).
        warmup_fraction: Share of the optimizer steps with a linear learning-rate warm-up; a number in [0, 1].
        restart_fraction: Share of the epochs, from the first, after which codes no training token used in that
            epoch are re-seeded from the data; a number in [0, 1].
        augment_probability: Chance, per training window, action dimension and epoch, that the window's values in
            that dimension are rescaled and moved inside [-1, 1]; a number in [0, 1] (0 turns augmentation off).
        augment_max_scale: Largest amplitude factor of that augmentation (``1 / augment_max_scale`` is the smallest,
            1 only moves); a number >= 1.
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
    warmup_fraction: float = 0.05
    restart_fraction: float = 0.25
    augment_probability: float = 0.5
    augment_max_scale: float = 2.0

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
        require_registry_alias("tokenizer.registry_alias", self.registry_alias)
        for name in ("warmup_fraction", "restart_fraction", "augment_probability"):
            _require(0.0 <= getattr(self, name) <= 1.0, f"tokenizer.{name}", getattr(self, name), "must be in [0, 1]")
        _require(self.augment_max_scale >= 1.0, "tokenizer.augment_max_scale", self.augment_max_scale, "must be >= 1")


# GroupNorm as in Diffusion Policy: one group per 16 channels, so every stage width must be a multiple of 16.
CHANNELS_PER_GROUP = 16
STANDARD_BASE_CHANNELS = 64
LIGHT_BASE_CHANNELS = 16


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


@dataclass(frozen=True)
class ImageEncoderConfig:
    """Cameras, crop and network sizes of the image encoder (:class:`carp.vision.encoder.ImageEncoder`).

    Defaults are Diffusion Policy's image recipe (robomimic's ``VisualCore``): per camera a ResNet-18 trunk trained
    from scratch with GroupNorm, a spatial-softmax head of 32 keypoints projected to 64 features, and crops of
    76 x 76 pixels from 84 x 84 images; :meth:`light` is the CPU-sized variant. In ``params.yaml`` the
    ``image_encoder`` section holds the network's settings; its cameras and image size are ``data.cameras`` and
    ``data.image_size`` (the images ingest stored).

    Attributes:
        cameras: robosuite camera names, one encoder each; their images are the obs keys ``<camera>_image``;
            at least one, no repeats. In ``params.yaml`` it is ``data.cameras``: leave it out of this section.
        image_size: height and width of the stored images in pixels (robomimic: 84); an integer >= 1. In
            ``params.yaml`` it is ``data.image_size``: leave it out of this section.
        crop_size: side of the square crop fed to the network, random in training and centred in evaluation
            (Diffusion Policy: 76); an integer in [1, image_size].
        base_channels: channels of the ResNet-18 stem; the four stages have 1, 2, 4 and 8 times as many. 64 is the
            standard ResNet-18 (11.2 M trunk parameters per camera), 16 the light CPU variant (0.70 M); a positive
            multiple of 16 (GroupNorm uses one group per 16 channels).
        num_keypoints: K, spatial-softmax keypoints per camera (Diffusion Policy: 32); an integer >= 1.
        feature_dim: features per camera after projecting the 2K keypoint coordinates (Diffusion Policy: 64); an
            integer >= 1.
    """

    SECTION: ClassVar[str] = "image_encoder"

    cameras: tuple[str, ...] = ("agentview", "robot0_eye_in_hand")
    image_size: int = 84
    crop_size: int = 76
    base_channels: int = STANDARD_BASE_CHANNELS
    num_keypoints: int = 32
    feature_dim: int = 64

    def __post_init__(self) -> None:
        section = self.SECTION
        object.__setattr__(self, "cameras", tuple(self.cameras))
        _require(len(self.cameras) > 0, f"{section}.cameras", list(self.cameras), "must name at least one camera")
        _require(
            all(isinstance(camera, str) and camera for camera in self.cameras),
            f"{section}.cameras",
            list(self.cameras),
            "must be non-empty camera names",
        )
        _require(
            len(set(self.cameras)) == len(self.cameras),
            f"{section}.cameras",
            list(self.cameras),
            "names a camera twice",
        )
        for name in ("image_size", "num_keypoints", "feature_dim"):
            value = getattr(self, name)
            _require(_is_int(value) and value >= 1, f"{section}.{name}", value, "must be an integer >= 1")
        _require(
            _is_int(self.crop_size) and 1 <= self.crop_size <= self.image_size,
            f"{section}.crop_size",
            self.crop_size,
            f"must be an integer in [1, image_size={self.image_size}]",
        )
        _require(
            _is_int(self.base_channels) and self.base_channels >= 1 and self.base_channels % CHANNELS_PER_GROUP == 0,
            f"{section}.base_channels",
            self.base_channels,
            f"must be a positive multiple of {CHANNELS_PER_GROUP} (GroupNorm has one group per {CHANNELS_PER_GROUP} "
            "channels)",
        )

    @property
    def image_keys(self) -> tuple[str, ...]:
        """Obs keys of the cameras' images in the robomimic schema, in camera order."""
        return tuple(f"{camera}_image" for camera in self.cameras)

    def light(self) -> "ImageEncoderConfig":
        """This config with the CPU-sized trunk (``base_channels`` 16: 0.70 M parameters per camera, not 11.2 M)."""
        return replace(self, base_channels=LIGHT_BASE_CHANNELS)


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
            among the registered ones (``carp.tasks``). DVC tracks the mapping as one parameter, so a change reruns
            every ``train_policy`` stage; a task whose settings did not change resumes from its finished training state.
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


def _distinct_paths(key: str, paths: Any) -> tuple[str, ...]:
    """`paths` as a tuple, refused at `key` unless every entry is a non-empty string named once."""
    listed = list(paths)
    _require(all(isinstance(path, str) and path for path in listed), key, listed, "must be non-empty paths")
    _require(len(set(listed)) == len(listed), key, listed, "must name each once")
    return tuple(listed)


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
    """Simulated evaluation (docs/architecture.md, "Evaluation protocol").

    Attributes:
        episodes: Seeded evaluation episodes per task; an integer >= 1. The success rate is reported with its 95%
            Wilson interval, which narrows with more episodes.
        seed: First evaluation seed; an integer >= 0. Episode i uses ``seed + i``. The range ``[seed, seed +
            episodes)`` must not overlap the collection seeds ``[data.collection_seed, data.collection_seed + 3 *
            demos)``, with demos the largest per-task demo count.
        workers: Simulator worker processes, each with its own copy of the policy; an integer >= 0, where 0 means
            one per CPU core.
        max_steps: Task -> step limit of one episode, in the task's control steps (20 Hz for the arms, 10 Hz for
            Push-T); each an integer >= 1. A task without an entry gets its protocol's limit (arms 400, Push-T 300);
            an episode that has not succeeded by then counts as a failure.
        video: Record GIF videos of the first ``video_episodes`` episodes of each task and policy, from the agent-view
            camera, into ``reports/eval/videos/``, which the report shows (needs offscreen rendering through EGL);
            true or false.
        video_episodes: Episodes recorded per task when ``video`` is true; an integer >= 0.
        backend: ``onnxruntime`` runs batch-1 inference as exported ONNX graphs, several times faster per chunk than
            the eager modules (see ``carp.policies.carp.onnx_policy``); ``torch`` runs the PyTorch modules. Both choose
            the same tokens.
        selection: Which of a training run's candidate policies (its snapshots, ``training.snapshot_every`` and
            ``snapshot_last``, and the final policy) is evaluated on the test seeds: ``final``, ``best_validation``
            (the highest success on the validation seeds; ties go to the later epoch), ``lowest_loss`` (the lowest
            training loss of its epoch) or ``average_last`` (one policy whose weights are the mean of the last
            ``average_last`` candidates', by epoch). The choice is fixed before any test episode runs.
        validation_episodes: Episodes per candidate policy on the validation seeds; an integer >= 0, at least 1 with
            ``selection: best_validation``. With 0 no validation episode runs.
        validation_seed: First validation seed; an integer >= 0. Validation episode i uses ``validation_seed + i``;
            the range must not overlap the test seeds ``[seed, seed + episodes)`` nor the collection seeds.
        validation_top_k: The report's Diffusion-Policy-style figure: the mean validation success of the this many best
            candidates, next to their maximum and the confirmed test success; an integer >= 1.
        average_last: With ``selection: average_last``, how many of the latest candidates are averaged; an integer
            >= 1 (1 is the final policy), at most the candidates the training keeps (checked when evaluating).
        ensemble_m: How a policy's chunks are executed: ``null`` (the default, carp's protocol and the CARP paper's)
            runs ``data.action_steps`` actions of each chunk, then predicts the next; a number >= 0 predicts a chunk at
            every control step and executes the temporal ensemble of the overlapping chunks (ACT's weights
            ``exp(-m * i)``, i = 0 the oldest prediction; 0 = their plain mean, VQ-BeT's Push-T inference), every
            family alike. Costs ``Ta`` times the predictions per episode.
        run_test: Whether the selected candidate runs on the test seeds; true or false. False runs the validation
            episodes only and writes a summary of the selected candidate's validation figures (``validation_score``,
            ``validation_success_rate``) with no test figure, no test episode and nothing for the report stage to
            compare; it needs ``validation_episodes >= 1`` and a rule that selects one candidate (not
            ``average_last``). The sweep sets it false for its trials, so that choosing settings never touches the
            test seeds; leave it true in the pipeline.
    """

    episodes: int = 50
    seed: int = 100_000
    workers: int = 0
    max_steps: dict[str, int] = field(default_factory=lambda: {"lift": 400, "can": 400, "square": 400})
    video: bool = False
    video_episodes: int = 2
    backend: str = "onnxruntime"
    selection: str = "final"
    validation_episodes: int = 0
    validation_seed: int = 200_000
    validation_top_k: int = 3
    average_last: int = 3
    ensemble_m: float | None = None
    run_test: bool = True

    def validation_seeds(self) -> list[int]:
        """The seeds of the validation episodes, which select a checkpoint."""
        return [self.validation_seed + index for index in range(self.validation_episodes)]

    def test_seeds(self) -> list[int]:
        """The seeds of the test episodes, which confirm the selected checkpoint."""
        return [self.seed + index for index in range(self.episodes)]

    def __post_init__(self) -> None:
        _require(self.episodes >= 1, "eval.episodes", self.episodes, "must be >= 1")
        _require(self.seed >= 0, "eval.seed", self.seed, "must be >= 0")
        _require(self.workers >= 0, "eval.workers", self.workers, "must be >= 0 (0 = one per core)")
        for task, steps in self.max_steps.items():
            _require(task in TASK_NAMES, f"eval.max_steps.{task}", task, f"task must be one of {TASK_NAMES}")
            _require(steps >= 1, f"eval.max_steps.{task}", steps, "must be >= 1")
        _require(self.video_episodes >= 0, "eval.video_episodes", self.video_episodes, "must be >= 0")
        _require(self.backend in EVAL_BACKENDS, "eval.backend", self.backend, f"must be one of {EVAL_BACKENDS}")
        _require(
            self.selection in SELECTION_RULES, "eval.selection", self.selection, f"must be one of {SELECTION_RULES}"
        )
        _require(self.validation_episodes >= 0, "eval.validation_episodes", self.validation_episodes, "must be >= 0")
        _require(
            self.selection != "best_validation" or self.validation_episodes >= 1,
            "eval.validation_episodes",
            self.validation_episodes,
            "must be >= 1 with selection: best_validation",
        )
        _require(self.validation_seed >= 0, "eval.validation_seed", self.validation_seed, "must be >= 0")
        _require(self.validation_top_k >= 1, "eval.validation_top_k", self.validation_top_k, "must be >= 1")
        require_positive_int("eval.average_last", self.average_last)
        _require(
            self.ensemble_m is None or (not isinstance(self.ensemble_m, bool) and self.ensemble_m >= 0),
            "eval.ensemble_m",
            self.ensemble_m,
            "must be null or a number >= 0",
        )
        _require(isinstance(self.run_test, bool), "eval.run_test", self.run_test, "must be true or false")
        _require(
            self.run_test or self.validation_episodes >= 1,
            "eval.run_test",
            self.run_test,
            "false needs validation episodes: set eval.validation_episodes >= 1",
        )
        _require(
            self.run_test or self.selection != "average_last",
            "eval.run_test",
            self.run_test,
            "false needs a rule that selects one validated candidate, not average_last",
        )
        validation_end = self.validation_seed + self.validation_episodes
        _require(
            self.validation_episodes == 0
            or validation_end <= self.seed
            or self.validation_seed >= self.seed + self.episodes,
            "eval.validation_seed",
            self.validation_seed,
            f"validation seeds [{self.validation_seed}, {validation_end}) overlap the test seeds "
            f"[{self.seed}, {self.seed + self.episodes})",
        )


@dataclass(frozen=True)
class StudyConfig:
    """The paper's studies, each run as DVC experiments by ``make study STUDY=<name>`` (outside the default DAG).

    Attributes:
        data_efficiency_sizes: Demo counts of the data-efficiency study (supplementary Fig. 5): one experiment per
            size with ``data.subset_size`` set to it and ``data.num_demos`` to the largest, so that every size draws
            from one collected file and the subsets are nested; at least two, strictly increasing integers >= 1.
        scale_schedules: Points of the scales study (supplementary Fig. 10): one experiment per schedule with
            ``scales`` set to it, each compared with the workspace's own ``scales``, which must be one of them; at
            least two schedules, each as ``scales`` requires, no two of the same length K.
        codebook_sizes: Points of the codebook study: one experiment per size with ``codebook_size`` set to it, each
            compared with the workspace's own ``codebook_size``, which must be one of them; at least two strictly
            increasing integers >= 2.
        references: Folders of other runs of the same study (their ``reports/studies/<study>``, or a copy kept with
            the project) whose families the study's report adds to its own at every point, so that a study split
            over clones or machines (one family or training seed each) is reported as one. For the data-efficiency
            study each must hold a finished ``size<N>/`` for every size and the subsets must be the same
            (``data.num_demos``, ``data.subset_seed`` and the collection alike); the scales and codebook studies take
            whichever points a folder holds. A training seed of a family on a task may come from one place only.
            Paths relative to the project root, each at most once. Empty (the default): the study's own experiments
            only.
    """

    data_efficiency_sizes: tuple[int, ...] = (30, 60, 100, 200)
    scale_schedules: tuple[tuple[int, ...], ...] = (
        (1,),
        (1, 2),
        (1, 2, 3),
        (1, 2, 3, 4),
        (1, 2, 3, 4, 5),
        (1, 2, 3, 4, 5, 6),
    )
    codebook_sizes: tuple[int, ...] = (64, 256, 512, 1024)
    references: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        sizes = list(self.data_efficiency_sizes)
        _require(
            len(sizes) >= 2 and sizes[0] >= 1 and all(a < b for a, b in zip(sizes, sizes[1:])),
            "study.data_efficiency_sizes",
            sizes,
            "must hold at least two strictly increasing sizes >= 1",
        )
        object.__setattr__(self, "scale_schedules", tuple(tuple(schedule) for schedule in self.scale_schedules))
        lengths = [len(schedule) for schedule in self.scale_schedules]
        _require(
            len(lengths) >= 2 and len(set(lengths)) == len(lengths),
            "study.scale_schedules",
            [list(schedule) for schedule in self.scale_schedules],
            "must hold at least two schedules, no two with the same number of scales",
        )
        codebooks = list(self.codebook_sizes)
        _require(
            len(codebooks) >= 2 and codebooks[0] >= 2 and all(a < b for a, b in zip(codebooks, codebooks[1:])),
            "study.codebook_sizes",
            codebooks,
            "must hold at least two strictly increasing sizes >= 2",
        )
        object.__setattr__(self, "references", _distinct_paths("study.references", self.references))


@dataclass(frozen=True)
class ComparisonConfig:
    """How the report compares policy families on a task (read by the report stage only).

    Attributes:
        margin: Equivalence margin in success rate (0.05 = 5 percentage points): two families are "on par" when the
            (1 - 2 alpha) interval over training seeds of their difference lies inside (-margin, margin); a number
            in (0, 1).
        alpha: Family-wise significance level of all the verdicts a report (or a study's report) states: every
            pair's test of a difference and its test of equivalence go into one step-down correction; a number in
            (0, 0.5).
        min_seeds: Training seeds per family that a family verdict needs (the training seed is the unit of a family
            claim); a pair with fewer gets "not decided (n training seeds)" and its figures describe the trained
            networks only; an integer >= 2.
        references: Evaluation directories of other runs (their ``reports/eval``, or a copy of it kept with the
            project) whose evaluations of this run's tasks the report adds to its own: more training seeds of a
            family, families trained elsewhere, the single-task policies beside a multi-task one. Paths relative to
            the project root, each at most once; a training seed of a family on a task may come from one place only.
            The episodes pair by episode seed, so reference runs evaluated on the same test seeds. The report stage
            reruns when this list changes (``dvc repro -f report`` after a referenced directory changes). Empty (the
            default): the run's own evaluations only.
    """

    margin: float = 0.05
    alpha: float = 0.05
    min_seeds: int = 3
    references: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        _require(0 < self.margin < 1, "comparison.margin", self.margin, "must lie in (0, 1)")
        _require(0 < self.alpha < 0.5, "comparison.alpha", self.alpha, "must lie in (0, 0.5)")
        _require(
            isinstance(self.min_seeds, int) and not isinstance(self.min_seeds, bool) and self.min_seeds >= 2,
            "comparison.min_seeds",
            self.min_seeds,
            "must be an integer >= 2 (one training seed says nothing about a family)",
        )
        object.__setattr__(self, "references", _distinct_paths("comparison.references", self.references))


@dataclass(frozen=True)
class TrackingConfig:
    """MLflow tracking (runs, metrics, artifacts and the model registry).

    Attributes:
        uri: MLflow tracking URI; not empty. A relative SQLite path (``sqlite:///mlflow.db``) is resolved against the
            project root, also for experiments run in a temporary copy.
        experiment_prefix: Prefix of the MLflow experiment names: ``<prefix>-<task>``, ``<prefix>-tokenizer`` and
            ``<prefix>-sweep``; not empty.
        policy_alias: Alias the ``register_policy`` stage points at the policies it registers (families in
            ``register``): ``<alias>-seed<k>`` at training seed k's version of ``carp-policy-<task>-<family>``, and
            ``<alias>`` itself at the version of the first seed in ``seeds``. Letters, digits, ``_`` and ``-``, not
            ``latest``, not ``v<digits>`` and not starting with a digit (reserved by the MLflow registry).
    """

    uri: str = "sqlite:///mlflow.db"
    experiment_prefix: str = "carp"
    policy_alias: str = "candidate"

    def __post_init__(self) -> None:
        _require(bool(self.uri), "tracking.uri", self.uri, "must be set")
        _require(bool(self.experiment_prefix), "tracking.experiment_prefix", self.experiment_prefix, "must be set")
        require_registry_alias("tracking.policy_alias", self.policy_alias)


@dataclass(frozen=True)
class SweepConfig:
    """Optuna study over scale schedules and codebook sizes (``make sweep``; outside the default DAG).

    Attributes:
        study_name: Name of the Optuna study, also part of each trial's DVC experiment name
            (``sweep-<study>-t<number>``); a changed search space needs a new name.
        storage: Optuna storage URL; a relative SQLite path (``sqlite:///optuna.db``) is resolved against the project
            root. Sweep workers in several workspaces (or on several machines) share one study through a PostgreSQL
            URL such as ``postgresql://mlflow@127.0.0.1:5432/optuna`` (password from ``~/.pgpass`` or ``PGPASSFILE``).
        num_trials: Total number of finished trials (complete, pruned or failed), counted across restarts of the
            sweep and across the workers sharing its study; an integer >= 1.
        scale_schedules: Candidate values of ``scales``; at least one, each as ``scales`` requires.
        codebook_sizes: Candidate values of ``codebook_size``; each an integer >= 2.
        prune_factor: A trial whose tokenizer reconstruction error is more than this many times the lowest error of
            the study so far is pruned before its policy is trained; a number > 1.
        heartbeat_seconds: How often a running trial marks itself alive in the storage, in seconds; an integer >= 1.
            A killed sweep's trial is retried once its heartbeat is two intervals old.
        git_remote: Git remote (a name such as ``origin``, or a URL) that every completed trial's DVC experiment is
            pushed to (``dvc exp push``, which also pushes its outputs to the default DVC remote when there is one),
            so that the experiments of every worker can be pulled into any workspace; empty: nothing is pushed.
        pruner: How Optuna stops a trial early from its snapshots' validation scores, which the trial reports as the
            evaluate stage produces them (see ``carp.sweep.pruning``): ``successive_halving``, ``hyperband`` or
            ``none``. The tokenizer check (``prune_factor``) applies whatever the choice.
        validation_episodes: Episodes per candidate policy on the validation seeds (from ``eval.validation_seed``)
            in every trial and in the confirmation, which select on them; the sweep sets it as their
            ``eval.validation_episodes``, whatever the ``eval`` section says. An integer >= 1; a few dozen tell trials
            apart.
        confirm_seeds: Training seeds of the confirmation that ends the sweep: the selected trial's settings and the
            default ones (``scales`` and ``codebook_size`` of the committed params file) are each trained once per
            seed and evaluated on the test seeds, and their paired comparison is the sweep's result; distinct integers
            >= 0, at least two and at least ``comparison.min_seeds`` (fewer could never confirm anything), and none
            of ``seeds`` (the sweep checks it): the winner's trial networks were chosen for their validation score,
            and a confirmation that reused one would measure the selected settings with that luck included.
    """

    study_name: str = "carp-sweep"
    storage: str = "sqlite:///optuna.db"
    num_trials: int = 8
    scale_schedules: tuple[tuple[int, ...], ...] = ((4,), (1, 4), (1, 2, 4), (1, 2, 3, 4))
    codebook_sizes: tuple[int, ...] = (64, 256, 512)
    prune_factor: float = 2.0
    heartbeat_seconds: int = 10
    git_remote: str = ""
    pruner: str = "successive_halving"
    validation_episodes: int = 20
    confirm_seeds: tuple[int, ...] = (1, 2, 3)

    def __post_init__(self) -> None:
        _require(self.num_trials >= 1, "sweep.num_trials", self.num_trials, "must be >= 1")
        _require(len(self.scale_schedules) >= 1, "sweep.scale_schedules", self.scale_schedules, "must not be empty")
        for size in self.codebook_sizes:
            _require(size >= 2, "sweep.codebook_sizes", self.codebook_sizes, "every size must be >= 2")
        _require(self.prune_factor > 1.0, "sweep.prune_factor", self.prune_factor, "must be > 1")
        _require(self.heartbeat_seconds >= 1, "sweep.heartbeat_seconds", self.heartbeat_seconds, "must be >= 1")
        _require(
            self.git_remote == self.git_remote.strip() and not self.git_remote.startswith("-"),
            "sweep.git_remote",
            self.git_remote,
            "must be a git remote name or URL, without surrounding spaces or a leading '-'",
        )
        _require(self.pruner in SWEEP_PRUNERS, "sweep.pruner", self.pruner, f"must be one of {SWEEP_PRUNERS}")
        _require(self.validation_episodes >= 1, "sweep.validation_episodes", self.validation_episodes, "must be >= 1")
        seeds = list(self.confirm_seeds)
        _require(
            len(seeds) >= 2
            and all(isinstance(seed, int) and not isinstance(seed, bool) and seed >= 0 for seed in seeds)
            and len(set(seeds)) == len(seeds),
            "sweep.confirm_seeds",
            seeds,
            "must hold at least two distinct integer seeds >= 0",
        )


FAMILY_SECTIONS = "family_sections"
"""Marks the two `Params` fields whose YAML sections are named after the registered policy families."""


def family_sections() -> dict[str, tuple[type, type]]:
    """Registered family -> (config class of its section, class of its `inference.<family>` section)."""
    # Imported here: the families' config modules import this module for `_require` and `ConfigError`.
    from carp.policies.registry import family_names, get_sections

    return {name: get_sections(name) for name in family_names()}


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
        tasks: Tasks the pipeline runs, among the registered ones (``carp.tasks``: the robosuite arms lift, can,
            square, stack, nut_assembly, stack_three and threading, and pusht), each at most once, all in one action
            space (one tokenizer serves them: the arms and Push-T do not mix); the per-task stages (``collect``,
            ``ingest``, ``train_policy``, ``evaluate``) fan out over this list.
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
        tokenizer: The action tokenizer and its training.
        training: The training loop shared by every policy family.
        eval: Simulated evaluation.
        tracking: MLflow tracking.
        sweep: The Optuna sweep.
        comparison: The report's comparison of families: equivalence margin and significance level.
        study: The paper's studies run as DVC experiments (``make study``).
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
    training: TrainingConfig = field(default_factory=TrainingConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    sweep: SweepConfig = field(default_factory=SweepConfig)
    comparison: ComparisonConfig = field(default_factory=ComparisonConfig)
    study: StudyConfig = field(default_factory=StudyConfig)
    image_encoder: ImageEncoderConfig = field(default_factory=ImageEncoderConfig)
    families: dict[str, Any] = field(default_factory=dict, metadata={FAMILY_SECTIONS: True})
    inference: dict[str, Any] = field(default_factory=dict, metadata={FAMILY_SECTIONS: True})

    def __post_init__(self) -> None:
        _require(len(self.tasks) >= 1, "tasks", self.tasks, "must list at least one task")
        for task in self.tasks:
            _require(task in TASK_NAMES, "tasks", self.tasks, f"every task must be one of {TASK_NAMES}")
        _require(len(set(self.tasks)) == len(self.tasks), "tasks", self.tasks, "must not repeat a task")
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
        for task in self.tasks:
            _require(
                self.data.subset_size <= self.data.demos_for(task) or task in self.data.raw_files,
                "data.subset_size",
                self.data.subset_size,
                f"must be <= the {self.data.demos_for(task)} demos collected for {task}",
            )

    def _check_multitask(self, known: dict[str, Any]) -> None:
        """Multi-task families are registered and distinct, over two tasks or more of state observations."""
        families = list(self.multitask)
        for name in families:
            _require(name in known, "multitask", families, f"every family must be one of {list(known)}")
        _require(len(set(families)) == len(families), "multitask", families, "must not repeat a family")
        if not families:
            return
        from carp.policies.registry import get_family  # see family_sections

        for name in families:
            _require(
                get_family(name).teacher is None,
                "multitask",
                families,
                f"{name} distils its {get_family(name).teacher} teacher, which trains on one task only",
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
                spaces[task] = get_task(task).action_format(self.data.controller).space
            except ValueError as error:
                raise ConfigError(f"data.controller={self.data.controller!r}: {error}") from None
            _require(
                self.data.observations != "image" or get_task(task).supports_cameras,
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

    @property
    def action_format(self) -> ActionFormat:
        """How the tasks' stored actions map to the policy's (the same for every task in ``tasks``)."""
        return get_task(self.tasks[0]).action_format(self.data.controller)

    def obs_keys_for(self, task: str) -> tuple[str, ...]:
        """Low-dim obs keys of `task` in the replay buffer: ``data.low_dim_keys``, or the task's fixed observation."""
        task_spec = get_task(task)
        return self.data.low_dim_keys if task_spec.configurable_obs_keys else task_spec.default_obs_keys

    def max_steps_for(self, task: str) -> int:
        """Step limit of one evaluation episode of `task`: its ``eval.max_steps`` entry, else the task's default."""
        return self.eval.max_steps.get(task, get_task(task).default_max_steps)

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
    def tokenizer_tasks(self) -> tuple[str, ...]:
        """Tasks whose demos train the tokenizer (``tokenizer.tasks`` or, when empty, ``tasks``)."""
        return self.tokenizer.tasks or self.tasks

    @property
    def action_space(self) -> str:
        """Name of the action space, e.g. ``panda-abs10``; part of the registered tokenizer's name."""
        return self.action_format.space


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
    """Plain nested dict (lists instead of tuples) of validated params, shaped as ``params.yaml``.

    Each family's section comes out at the top level under its name, as it is written in the file; settings the
    pipeline sets per run (``training.seed``) are left out, as the file does not hold them.
    """
    values = _plain(dataclasses.asdict(params))
    for section_name, hint in typing.get_type_hints(Params).items():
        if dataclasses.is_dataclass(hint):
            for field_ in dataclasses.fields(hint):
                if field_.metadata.get(SET_BY_PIPELINE):
                    values[section_name].pop(field_.name)
    families = values.pop("families")
    return {**values, **families}


def flatten_params(params: Params) -> dict[str, str]:
    """Dotted-key view (``carp.depth`` -> ``"8"``) for MLflow params."""
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
    dynamic = [f.name for f in dataclasses.fields(cls) if f.metadata.get(FAMILY_SECTIONS)]
    known = {f.name for f in dataclasses.fields(cls) if f.name not in dynamic}
    values = {}
    if dynamic:
        raw, values = _build_family_sections(raw, prefix)
        named = known | set(family_sections()) | {"inference"}
    derived = {f.name for f in dataclasses.fields(cls) if f.metadata.get(SET_BY_PIPELINE)}
    for key in raw:
        if key in derived:
            raise ConfigError(
                f"{prefix}{key}={raw[key]!r}: set by the pipeline for each run, not in params.yaml"
                + (" (training seeds are the top-level list `seeds`, e.g. seeds: [0, 1, 2])" if key == "seed" else "")
            )
        if key not in known:
            names = ", ".join(sorted((named if dynamic else known) - derived))
            raise ConfigError(f"{prefix}{key}: unknown key (known: {names})")
    for name, value in raw.items():
        hint = hints[name]
        key = f"{prefix}{name}"
        if dataclasses.is_dataclass(hint):
            values[name] = _build(hint, value if value is not None else {}, prefix=f"{key}.")
        else:
            values[name] = _coerce(value, hint, key)
    return cls(**values)


def _build_family_sections(raw: dict, prefix: str) -> tuple[dict, dict[str, Any]]:
    """Split the family sections (`<family>:` and `inference: {<family>: ...}`) off `raw` and build them.

    Returns:
        The rest of `raw`, and `{"families": ..., "inference": ...}` with each family's built sections.
    """
    known = family_sections()
    rest = {key: value for key, value in raw.items() if key not in known and key != "inference"}
    families = {
        name: _build(classes[0], raw[name] if raw[name] is not None else {}, f"{prefix}{name}.")
        for name, classes in known.items()
        if name in raw
    }
    inference_raw = raw.get("inference") or {}
    if not isinstance(inference_raw, dict):
        raise ConfigError(f"{prefix}inference: expected a mapping, got {type(inference_raw).__name__}")
    for name in inference_raw:
        if name not in known:
            raise ConfigError(f"{prefix}inference.{name}: unknown policy family (known: {', '.join(known)})")
    inference = {
        name: _build(known[name][1], value if value is not None else {}, f"{prefix}inference.{name}.")
        for name, value in inference_raw.items()
    }
    return rest, {"families": families, "inference": inference}


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
