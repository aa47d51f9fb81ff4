"""Open-loop replay of demonstrations through a tokenizer's round trip: is the tokenizer precise enough for a task?

Each scripted demo is replayed from the seed it was collected with. At every decision step t (every ``Ta`` steps)
the recorded chunk a policy would have to predict there (rows t - To + 1 .. t - To + H, clamped to the episode like
the training windows) is normalized with the task's statistics, tokenized, decoded and un-normalized, and its rows
``[To - 1, To - 1 + Ta)`` are executed, exactly the rows `carp.evaluation.sources.executed_actions` takes from a
policy's chunk. Without a tokenizer the recorded actions are executed unchanged, which checks that the simulation
reproduces the demos. Nothing corrects an error once made, so the success rate is a pessimistic bound on what a
policy can reach through this tokenizer, and a direct comparison of tokenizers on the same demos.
"""

import functools
from pathlib import Path

import numpy as np
import torch

from carp.data.normalizer import MinMaxNormalizer
from carp.data.robomimic_io import DatasetError, read_demonstrations
from carp.evaluation.rollout import ChunkTiming, EpisodeResult, evaluate_episodes
from carp.evaluation.sources import executed_actions
from carp.tasks import task_for_env_args
from carp.tasks.base import ActionFormat
from carp.tokenizer.kinds.base import ActionTokenizer


class TokenizedReplaySource:
    """Replays the recorded actions of the episode's seed, each chunk through the tokenizer when one is given.

    Args:
        demo_actions: collection seed -> (T, A) recorded actions in the policy's action format (10-D for absolute).
        action_normalizer: the task's action statistics.
        tokenizer: a tokenizer of any kind (`carp.tokenizer.kinds`, picklable: each worker gets a copy), or None to
            replay the recorded actions unchanged.
        action_format: the task's action format under the file's controller.
        obs_steps: ``To``.
        action_steps: ``Ta``.
        horizon: ``H``.
    """

    def __init__(
        self,
        demo_actions: dict[int, np.ndarray],
        action_normalizer: MinMaxNormalizer,
        tokenizer: ActionTokenizer | None,
        action_format: ActionFormat,
        obs_steps: int,
        action_steps: int,
        horizon: int,
    ) -> None:
        self.demo_actions = demo_actions
        self.action_normalizer = action_normalizer
        self.tokenizer = tokenizer
        self.action_format = action_format
        self.obs_steps, self.action_steps, self.horizon = obs_steps, action_steps, horizon
        self._actions = np.empty((0, 0))
        self._step = 0

    def reset(self, env, seed: int) -> None:
        """Start replaying the demo collected with ``seed``."""
        self._actions = self.demo_actions[seed]
        self._step = 0

    def chunk(self) -> np.ndarray:
        """(H, A) the recorded chunk of the current decision step, through the tokenizer's round trip if any."""
        rows = np.clip(self._step - (self.obs_steps - 1) + np.arange(self.horizon), 0, len(self._actions) - 1)
        chunk = self._actions[rows]
        if self.tokenizer is None:
            return chunk
        normalized = torch.as_tensor(self.action_normalizer.normalize(chunk[None]), dtype=torch.float32)
        decoded = self.tokenizer.decode(self.tokenizer.encode(normalized)).actions  # (1, H, A)
        return self.action_normalizer.unnormalize(decoded[0].double().numpy())

    def act(self, observation_history: np.ndarray, env) -> tuple[np.ndarray, ChunkTiming | None]:
        """(Ta, stored_dim) the next executed actions."""
        executed = executed_actions(self.chunk(), self.obs_steps, self.action_steps, self.action_format)
        self._step += self.action_steps
        return executed, None


def replay_demonstrations(
    raw_path: Path,
    action_normalizer: MinMaxNormalizer,
    tokenizer: ActionTokenizer | None,
    obs_steps: int,
    action_steps: int,
    horizon: int,
    num_demos: int | None = None,
    workers: int = 1,
) -> list[EpisodeResult]:
    """Replay the first ``num_demos`` demos of a scripted-demo file (all when None); one result per demo.

    Args:
        raw_path: robomimic-schema file whose demos carry their collection ``seed`` attribute (`carp.data.collect`).
        action_normalizer: the task's action statistics (``data/processed/<task>/normalization.json``).
        tokenizer: tokenizer of any kind to round-trip every chunk through; None replays unchanged.
        obs_steps: ``To`` of the policy.
        action_steps: ``Ta``, rows executed per chunk.
        horizon: ``H``, rows per chunk.
        num_demos: how many demos, from the first.
        workers: parallel processes, one env each.

    Raises:
        DatasetError: a demo without a ``seed`` attribute (not collected by carp), naming the file and demo.
    """
    demos = read_demonstrations(Path(raw_path), ())
    selected = list(zip(demos.names, demos.episodes, strict=True))[:num_demos]
    missing = [name for name, episode in selected if "seed" not in episode.attrs]
    if missing:
        raise DatasetError(
            f"{raw_path}: demo '{missing[0]}' has no 'seed' attribute; replay needs demos collected by carp"
        )
    task = task_for_env_args(demos.env_args)
    action_format = task.action_format(task.controller_of(demos.env_args))
    demo_actions = {int(episode.attrs["seed"]): action_format.to_policy(episode.actions) for _, episode in selected}
    source_factory = functools.partial(
        TokenizedReplaySource,
        demo_actions,
        action_normalizer,
        tokenizer,
        action_format,
        obs_steps,
        action_steps,
        horizon,
    )
    longest = max(len(actions) for actions in demo_actions.values())
    return evaluate_episodes(
        demos.env_args,
        source_factory,
        list(demo_actions),
        # The rollout keeps an observation history the replay does not read; one key keeps that cheap.
        task.default_obs_keys[-1:],
        obs_steps,
        max_steps=longest + horizon,
        workers=workers,
        description="replay",
    )
