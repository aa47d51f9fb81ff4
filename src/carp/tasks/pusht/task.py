"""Push-T behind the task seam: DP's state-based protocol (`carp.tasks.pusht.env`) and the planning expert.

Actions are stored and learned alike: the agent's absolute 2-D target in workspace pixels (action space
``pusht-abs2``), so ``data.controller`` must stay ``absolute``. The observation is DP's fixed 20 values
(``block_keypoints``, ``agent_pos``); ``data.obs_keys`` and camera observations do not apply. Beside success the
report gives DP's score, the mean over episodes of each episode's maximum reward (the ``max_reward`` measure).
"""

import importlib.metadata
from collections.abc import Mapping, Sequence

import numpy as np

from carp.tasks.base import ROLLOUTS, ActionFormat
from carp.tasks.pusht import env as pusht_env

PUSHT_ACTIONS = ActionFormat(
    space=f"pusht-abs{pusht_env.ACTION_DIM}",
    stored_dim=pusht_env.ACTION_DIM,
    policy_dim=pusht_env.ACTION_DIM,
    dimension_names=("target_x", "target_y"),
)

SCORE_MEASURE = "max_reward"


class MaxReward:
    """DP's per-episode score: the highest reward reached at any step (a success scores 1)."""

    def __init__(self) -> None:
        self.best = 0.0

    def reset(self, env: pusht_env.PushTEnv) -> None:
        """Start at 0: as in DP's runner, only the rewards of steps count, not the initial state's."""
        self.best = 0.0

    def observe(self, env: pusht_env.PushTEnv, step: int) -> None:
        """Keep the highest reward so far."""
        self.best = max(self.best, env.reward())

    def values(self) -> dict[str, float]:
        """``{"max_reward": ...}`` in [0, 1]."""
        return {SCORE_MEASURE: self.best}


class PushTDemonstrator:
    """The planning expert (`carp.tasks.pusht.expert.PushTExpert`) bound to one episode, acting without arguments.

    Its tie breaks are seeded with the episode's seed, so a demo depends on its seed only.
    """

    name = "pusht_planner"

    def __init__(self, env: pusht_env.PushTEnv, seed: int) -> None:
        from carp.tasks.pusht.expert import PushTExpert

        self.env = env
        self.expert = PushTExpert(seed=seed)

    def act(self) -> np.ndarray:
        """(2,) the next agent target."""
        return self.expert.act(self.env)


class _RenderedFrames:
    """Video frames drawn by gym-pusht (goal, block, agent, the last target)."""

    def __init__(self, env: pusht_env.PushTEnv) -> None:
        self.env = env

    def frame(self) -> np.ndarray:
        """(256, 256, 3) uint8."""
        return self.env.render()

    def close(self) -> None:
        """Nothing to release: the env owns its drawing surface."""


class PushTTask:
    """DP's state-based Push-T; see `carp.tasks.base.Task` for what each member means."""

    name = "pusht"
    env_name = pusht_env.ENV_NAME
    default_max_steps = pusht_env.MAX_STEPS
    step_limit = pusht_env.MAX_STEPS
    control_frequency_hz = pusht_env.CONTROL_FREQUENCY_HZ
    default_obs_keys = tuple(pusht_env.OBSERVATION_DIMS)
    configurable_obs_keys = False
    supports_cameras = False
    score_measure = SCORE_MEASURE
    paper_demos = "Diffusion Policy's human demonstrations"
    evaluation = ROLLOUTS

    def action_format(self, controller: str) -> ActionFormat:
        """`PUSHT_ACTIONS`; Push-T's only controller is ``absolute`` (the agent's target position)."""
        if controller != "absolute":
            raise ValueError(f"pusht: controller '{controller}': the agent takes absolute targets only ('absolute')")
        return PUSHT_ACTIONS

    def controller_of(self, env_args: Mapping) -> str:
        """Always ``absolute``."""
        return "absolute"

    def make_env_args(self, controller: str) -> dict:
        """`carp.tasks.pusht.env.make_env_args`, after checking the controller."""
        self.action_format(controller)
        return pusht_env.make_env_args()

    def make_env(self, env_args: Mapping, camera_names: Sequence[str] = (), image_size: int = 84) -> pusht_env.PushTEnv:
        """A `PushTEnv` whose own step limit is lifted: the rollout's ``max_steps`` ends episodes."""
        if camera_names:
            raise ValueError(f"pusht: camera observations {list(camera_names)} are not supported (state only)")
        env = pusht_env.make_env(env_args)
        env.max_steps = np.iinfo(np.int64).max
        return env

    def reset(self, env: pusht_env.PushTEnv, seed: int) -> dict[str, np.ndarray]:
        """DP's test reset for ``seed``."""
        return env.reset(seed)

    def step(self, env: pusht_env.PushTEnv, action: np.ndarray) -> tuple[dict[str, np.ndarray], float]:
        """One 10 Hz control step towards the target ``action`` (2,); DP's reward."""
        step = env.step(action)
        return step.observation, step.reward

    def observations(self, observation: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The observation as float64 arrays (it has no images)."""
        return {key: np.asarray(value, dtype=np.float64).reshape(-1) for key, value in observation.items()}

    def is_success(self, env: pusht_env.PushTEnv) -> bool:
        """Coverage of the goal above 95%."""
        return env.is_success()

    def simulator_state(self, env: pusht_env.PushTEnv) -> np.ndarray:
        """(5,) agent x, y, block x, y, angle."""
        return env.state()

    expert_name = PushTDemonstrator.name

    def make_expert(self, env: pusht_env.PushTEnv, seed: int) -> PushTDemonstrator:
        """The planning expert for this episode."""
        return PushTDemonstrator(env, seed)

    def measure(self) -> MaxReward:
        """DP's score of one episode."""
        return MaxReward()

    @property
    def lerobot_adapter(self):
        """Derives DP's observations and the states from ``lerobot/pusht_keypoints``' T vertices.

        `carp.tasks.pusht.lerobot.PushTKeypoints`, used for a LeRobotDataset without ``block_keypoints`` and
        ``agent_pos``.
        """
        from carp.tasks.pusht.lerobot import PushTKeypoints

        return PushTKeypoints()

    def video(self, env: pusht_env.PushTEnv, camera: str) -> _RenderedFrames:
        """gym-pusht's top-down drawing (there is one view, so ``camera`` is not read)."""
        return _RenderedFrames(env)

    def cameras(self, env: pusht_env.PushTEnv, settings) -> _RenderedFrames:
        """Refused: state-based Push-T has no camera observations."""
        raise ValueError("pusht: camera observations are not supported (state only)")

    def versions(self) -> dict[str, str]:
        """gym-pusht's and pymunk's versions."""
        return {
            name.replace("-", "_") + "_version": importlib.metadata.version(name) for name in ("gym-pusht", "pymunk")
        }


TASK = PushTTask()
