"""The `data` section: demos, observations and the windows cut from them."""

from dataclasses import dataclass, field

from carp.config.checks import CONTROLLERS, IMAGE_KEY_SUFFIX, OBSERVATION_KINDS, _require, require_positive_int


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
            ``mask/valid`` (that mask wins when present; one that lists every demo is refused); a number in [0, 1).
        raw_files: Task -> path of your own robomimic-schema HDF5 file or LeRobotDataset folder (v3.0 or v2.x, the
            folder holding ``meta/info.json``; ``carp.data.demo_sources``), relative to the project root, validated
            and used instead of scripted collection; each task registered (``carp.tasks``) or listed in ``tasks``.
            For a registered task, a file's ``env_args`` must name the task's env (a LeRobotDataset carp did not
            export takes the task's own), and its actions must have the task's width (7 for the arms, 2 for
            Push-T). A name in ``tasks`` that is not registered needs a LeRobotDataset folder here: it becomes a
            task without a simulator, trained on the dataset and evaluated offline (``carp.tasks.offline``).
        num_demos_per_task: Task -> scripted demos for that task, overriding ``num_demos``; each an integer >= 1, tasks
            registered (``carp.tasks``) or listed in ``tasks``. DVC tracks the whole mapping: changing one entry
            reruns every ``collect`` stage, but collection is deterministic, so only that task's data and what depends
            on it change.
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


def _require_per_task_minimum(mapping: dict[str, int], name: str, constraint: str) -> None:
    """Refuse a task -> integer override whose value is below 1 (its task is checked by `Params`)."""
    for task, value in mapping.items():
        _require(value >= 1, f"{name}.{task}", value, constraint)
