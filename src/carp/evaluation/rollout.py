"""One rollout loop for every action source (learned policy or scripted expert) and the parallel evaluator.

Time convention (DESIGN.md section 1): at each decision the source sees the last ``To`` observations (the first one
repeated after a reset) and returns the actions to execute before the next decision (``Ta`` for the policy, one for
the expert). Episodes run in worker processes, one env per process; a crash inside an episode is recorded as a
failure with its reason and the evaluation goes on.
"""

import logging
import multiprocessing
import time
import traceback
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from tqdm import tqdm

from carp import simulation

logger = logging.getLogger(__name__)


@dataclass
class ChunkTiming:
    """Seconds spent producing one chunk of actions."""

    prediction: float = 0.0
    decoding: float = 0.0


class ActionSource(Protocol):
    """Something that decides actions: a trained policy or a scripted expert."""

    def reset(self, env, seed: int) -> None:
        """Called after every env reset with the episode's seed (sources that sample derive their draws from it)."""

    def act(self, observation_history: np.ndarray, env) -> tuple[np.ndarray, ChunkTiming | None]:
        """Decide the next actions.

        Args:
            observation_history: (To, Do) the last ``To`` low-dim observations, oldest first.
            env: the live env (only privileged sources such as scripted experts may read it).

        Returns:
            actions (n, 7) to execute in order, and the chunk's timing (None when not measured).
        """


@dataclass
class EpisodeResult:
    """Outcome of one episode."""

    seed: int
    success: bool
    steps: int
    seconds: float
    error: str = ""
    prediction_seconds: list[float] = field(default_factory=list)
    decoding_seconds: list[float] = field(default_factory=list)
    frames: list[np.ndarray] = field(default_factory=list)


def flatten_observation(obs: dict, obs_keys: Sequence[str]) -> np.ndarray:
    """Concatenate the low-dim keys (robomimic names) of a robosuite observation into (Do,)."""
    features = simulation.low_dim_observations(obs)
    return np.concatenate([features[key] for key in obs_keys])


def run_episode(
    env,
    source: ActionSource,
    seed: int,
    obs_keys: Sequence[str],
    obs_steps: int,
    max_steps: int,
    render_camera: str | None = None,
) -> EpisodeResult:
    """Roll out one seeded episode until success or ``max_steps``; exceptions become a failed result.

    Args:
        env: robosuite env built by :func:`carp.simulation.make_env`.
        source: decides actions from the observation history.
        seed: reset seed (see :func:`carp.simulation.reset_env`).
        obs_keys: low-dim keys concatenated into the observation features, in training order.
        obs_steps: ``To``.
        max_steps: step limit.
        render_camera: when set, an offscreen RGB frame of this camera is kept after every step.
    """
    started = time.perf_counter()
    result = EpisodeResult(seed=seed, success=False, steps=0, seconds=0.0)
    try:
        obs = simulation.reset_env(env, seed)
        source.reset(env, seed)
        history = deque([flatten_observation(obs, obs_keys)] * obs_steps, maxlen=obs_steps)
        while result.steps < max_steps and not result.success:
            actions, timing = source.act(np.stack(history), env)
            if timing is not None:
                result.prediction_seconds.append(timing.prediction)
                result.decoding_seconds.append(timing.decoding)
            for action in actions:
                obs, _, _, _ = env.step(action)
                history.append(flatten_observation(obs, obs_keys))
                result.steps += 1
                if render_camera is not None:
                    frame = env.sim.render(camera_name=render_camera, height=256, width=256)
                    result.frames.append(np.flipud(frame).copy())
                if simulation.is_success(env):
                    result.success = True
                    break
                if result.steps >= max_steps:
                    break
    except Exception as error:  # noqa: BLE001 - a crash in one episode is a recorded failure, not a dead evaluation
        result.success = False
        result.error = f"{type(error).__name__}: {error}"
        logger.warning("episode with seed %d crashed:\n%s", seed, traceback.format_exc())
    result.seconds = time.perf_counter() - started
    return result


@dataclass(frozen=True)
class EpisodeJob:
    """What a worker needs to run one episode."""

    seed: int
    record_video: bool


# Per-process state of a worker: its env and action source, built once by the initializer.
_worker_state: dict = {}


def _init_worker(env_args: dict, source_factory: Callable[[], ActionSource], settings: dict) -> None:
    import torch

    torch.set_num_threads(1)
    render = settings["video_camera"] is not None
    _worker_state["env"] = simulation.make_env(env_args, render_offscreen=render)
    _worker_state["source"] = source_factory()
    _worker_state["settings"] = settings


def _run_job(job: EpisodeJob) -> EpisodeResult:
    settings = _worker_state["settings"]
    return run_episode(
        _worker_state["env"],
        _worker_state["source"],
        job.seed,
        settings["obs_keys"],
        settings["obs_steps"],
        settings["max_steps"],
        render_camera=settings["video_camera"] if job.record_video else None,
    )


def evaluate_episodes(
    env_args: dict,
    source_factory: Callable[[], ActionSource],
    seeds: Sequence[int],
    obs_keys: Sequence[str],
    obs_steps: int,
    max_steps: int,
    workers: int = 1,
    video_episodes: int = 0,
    video_camera: str = "agentview",
    description: str = "evaluate",
) -> list[EpisodeResult]:
    """Run one episode per seed across ``workers`` processes (one env each); results in seed order.

    Args:
        env_args: env description (the data's ``env_args``).
        source_factory: picklable zero-argument callable building the action source inside each worker.
        seeds: one episode per seed.
        obs_keys: observation keys in training order.
        obs_steps: ``To``.
        max_steps: step limit per episode.
        workers: processes; 1 runs in this process.
        video_episodes: the first this many seeds keep rendered frames.
        video_camera: camera used for videos.
        description: progress bar label.
    """
    settings = {
        "obs_keys": list(obs_keys),
        "obs_steps": obs_steps,
        "max_steps": max_steps,
        "video_camera": video_camera if video_episodes > 0 else None,
    }
    jobs = [EpisodeJob(seed=int(seed), record_video=index < video_episodes) for index, seed in enumerate(seeds)]
    results: dict[int, EpisodeResult] = {}
    progress = tqdm(total=len(jobs), desc=description, unit="episode")
    if workers <= 1:
        _init_worker(env_args, source_factory, settings)
        for job in jobs:
            results[job.seed] = _run_job(job)
            progress.update()
            progress.set_postfix(success=_rate(results))
    else:
        # spawn: each worker builds its own MuJoCo context and torch runtime instead of inheriting this process's.
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(
            max_workers=workers,
            mp_context=context,
            initializer=_init_worker,
            initargs=(env_args, source_factory, settings),
        ) as pool:
            futures = {pool.submit(_run_job, job): job for job in jobs}
            for future in as_completed(futures):
                job = futures[future]
                results[job.seed] = future.result()
                progress.update()
                progress.set_postfix(success=_rate(results))
    progress.close()
    return [results[job.seed] for job in jobs]


def _rate(results: dict[int, EpisodeResult]) -> str:
    return f"{sum(r.success for r in results.values())}/{len(results)}"
