"""Action sources for the rollout loop: a trained policy of any family and the scripted experts."""

import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import torch

from carp.evaluation.rollout import ChunkTiming
from carp.policies.base import Policy
from carp.tasks import get_task
from carp.tasks.base import ActionFormat


def executed_actions(chunk: np.ndarray, obs_steps: int, action_steps: int, action_format: ActionFormat) -> np.ndarray:
    """The part of a predicted chunk the env executes, in the env's action format.

    Args:
        chunk: (H, A) raw actions predicted from observations at steps ``t - To + 1 .. t``; row ``To - 1`` is step t.
        obs_steps: ``To``.
        action_steps: ``Ta``.
        action_format: the task's action format; its ``to_env`` maps the policy's rows to the env's (absolute arm
            actions: 10-D position, 6-D rotation, gripper to the controller's 7-D form).

    Returns:
        (Ta, stored_dim) float64.
    """
    executed = np.asarray(chunk[obs_steps - 1 : obs_steps - 1 + action_steps], dtype=np.float64)
    return action_format.to_env(executed)


class ChunkEnsemble:
    """Temporal ensembling of overlapping chunks, queried at every control step (ACT's rule; VQ-BeT's averaging).

    A chunk predicted at step t covers steps t .. t + n - 1 with its rows from ``To - 1`` on. The action of a step is
    the weighted mean of the rows that every chunk covering it predicts for it, weight ``exp(-m * i)`` for the i-th
    oldest prediction (i = 0 the oldest), normalized: ``m = 0`` is the plain mean of the overlapping chunks. The
    robot-side client's `carp_client.ChunkScheduler` applies the same rule to served chunks (it never imports carp;
    a test checks the two agree).

    Args:
        m: the weights' decay; >= 0.
    """

    def __init__(self, m: float) -> None:
        if not m >= 0:
            raise ValueError(f"ensemble m must be >= 0, got {m}")
        self.m = float(m)
        self._chunks: list[tuple[int, np.ndarray]] = []  # (first step, (n, A) rows), oldest first
        self._step = 0

    def reset(self) -> None:
        """A new episode: forget every chunk."""
        self._chunks.clear()
        self._step = 0

    def act(self, rows: np.ndarray) -> np.ndarray:
        """Take the chunk predicted at the current step and return the action of this step; then step on.

        Args:
            rows: (n, A) the chunk's rows from the current step on (row 0 acts now).

        Returns:
            (A,) float64 the weighted mean of every kept chunk's row for the current step.
        """
        step = self._step
        self._chunks.append((step, np.asarray(rows, dtype=np.float64)))
        self._chunks = [(start, chunk) for start, chunk in self._chunks if step - start < len(chunk)]
        predictions = np.stack([chunk[step - start] for start, chunk in self._chunks])  # (count, A), oldest first
        weights = np.exp(-self.m * np.arange(len(predictions)))
        self._step += 1
        return (weights / weights.sum()) @ predictions


class ExpertSource:
    """A task's scripted expert (privileged state) behind the same interface as the policy; one action per decision."""

    def __init__(self, task: str) -> None:
        self.task = get_task(task)
        self._expert = None

    def reset(self, env, seed: int) -> None:
        """Bind a fresh expert to the just-reset env."""
        self._expert = self.task.make_expert(env, seed)

    def act(self, observation_history: np.ndarray, env) -> tuple[np.ndarray, None]:
        """(1, stored_dim) the expert's next action."""
        return self._expert.act()[None, :], None


class PolicySource:
    """A trained policy of any family: predicts ``H`` actions, executes ``actions[To-1 : To-1+Ta]``.

    Args:
        load: zero-argument callable returning the policy (a `carp.policies.base.Deployment`'s `load`); called once,
            in the worker process that runs the episodes.
        action_format: maps the predicted actions to the env's (`executed_actions`).
        obs_steps: ``To``.
        action_steps: ``Ta``.
        inference: the family's inference settings (e.g. ``{"top_k": 3}``), applied through
            ``configure_inference``; any sampling draws from a generator seeded per episode.
        task_index: task id for multi-task policies.
        ensemble_m: None executes ``Ta`` actions per chunk; a number >= 0 predicts a chunk at every step and executes
            the temporal ensemble of the overlapping chunks (:class:`ChunkEnsemble`), one action per chunk.
    """

    def __init__(
        self,
        load: Callable[[], Policy],
        action_format: ActionFormat,
        obs_steps: int,
        action_steps: int,
        inference: Mapping[str, Any] | None = None,
        task_index: int | None = None,
        ensemble_m: float | None = None,
    ) -> None:
        self.policy = load()
        self.policy.configure_inference(**dict(inference or {}))
        self.action_format = action_format
        self.obs_steps = obs_steps
        self.action_steps = action_steps
        self.task_index = task_index
        self.ensemble = None if ensemble_m is None else ChunkEnsemble(ensemble_m)
        # Rollouts run on the CPU, so the draws come from a CPU generator whatever the policy's backend.
        self._generator = torch.Generator()

    def reset(self, env, seed: int) -> None:
        """New episode: seed sampling with the episode's seed.

        An episode's draws then do not depend on which worker runs it or on what that worker ran before.
        """
        self._generator.manual_seed(seed)
        if self.ensemble is not None:
            self.ensemble.reset()

    def act(
        self, observation_history: np.ndarray, env, images: np.ndarray | None = None
    ) -> tuple[np.ndarray, ChunkTiming]:
        """(Ta, stored_dim) actions for the env (one when ensembling) and the chunk's prediction/decoding time.

        Args:
            observation_history: (To, Do) raw low-dim observations, oldest first.
            env: not read (the policy sees only its observations).
            images: (To, cameras, 3, h, w) uint8 camera observations for an image policy; None for state.
        """
        seen = {} if images is None else {"images": images[None]}
        timed = self.policy.predict_action_timed(
            observation_history[None], task_index=self.task_index, generator=self._generator, **seen
        )
        started = time.perf_counter()
        if self.ensemble is None:
            executed = executed_actions(timed.actions[0], self.obs_steps, self.action_steps, self.action_format)
        else:
            action = self.ensemble.act(timed.actions[0][self.obs_steps - 1 :])  # (A,)
            executed = self.action_format.to_env(action[None])
        decoding_seconds = timed.decoding_seconds + time.perf_counter() - started
        return executed, ChunkTiming(
            prediction=timed.prediction_seconds,
            decoding=decoding_seconds,
            encoding=timed.encoding_seconds,
            repaired=timed.repaired_chunks,
        )
