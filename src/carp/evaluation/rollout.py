"""One rollout loop for every action source (learned policy or scripted expert) and the parallel evaluator.

Time convention (docs/architecture.md, "Time convention"): at each decision the source sees the last ``To`` observations
(the first one repeated after a reset) and returns the actions to execute before the next decision (``Ta`` for the
policy, one for the expert). Episodes run in worker processes, one env per process; a crash inside an episode is
recorded as a failure with its reason and the evaluation goes on. That holds for a worker process that dies as well (a
native crash in the simulator or in ONNX Runtime, the out-of-memory killer): the episode it was running is run once more
on a fresh worker and, if that worker dies too, recorded as crashed with the way it died (``worker killed by SIGKILL``).

A policy trained on camera images sees them the way ingest stored them: after every step the cameras are rendered
from the simulator's current state with the same renderer and settings that render a demo's stored states
(the task's ``cameras``), and the rendering time of each step is recorded apart from the policy's.
"""

import logging
import multiprocessing
import signal
import time
import traceback
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import wait
from typing import TYPE_CHECKING, Protocol

import numpy as np
from tqdm import tqdm

from carp.tasks import task_for_env_args
from carp.tasks.base import Task

if TYPE_CHECKING:
    from carp.data.rendering import RenderSettings

logger = logging.getLogger(__name__)


@dataclass
class ChunkTiming:
    """Seconds spent producing one chunk of actions."""

    prediction: float = 0.0
    decoding: float = 0.0
    encoding: float = 0.0  # the part of `prediction` spent encoding the observations (an image policy's cameras)
    repaired: int | None = None  # chunks whose tokens the tokenizer repaired (0 or 1 at batch 1); None: not reported


class ActionSource(Protocol):
    """Something that decides actions: a trained policy or a scripted expert."""

    def reset(self, env, seed: int) -> None:
        """Called after every env reset with the episode's seed (sources that sample derive their draws from it)."""

    def act(self, observation_history: np.ndarray, env, **seen: np.ndarray) -> tuple[np.ndarray, ChunkTiming | None]:
        """Decide the next actions.

        Args:
            observation_history: (To, Do) the last ``To`` low-dim observations, oldest first.
            env: the live env (only privileged sources such as scripted experts may read it).
            seen: ``images`` (To, cameras, 3, h, w) uint8, the last ``To`` camera observations, in an evaluation
                with cameras (only sources of image policies are run there).

        Returns:
            actions (n, stored action width) to execute in order, and the chunk's timing (None when not measured).
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
    encoding_seconds: list[float] = field(default_factory=list)
    frames: list[np.ndarray] = field(default_factory=list)
    render_seconds: list[float] = field(default_factory=list)
    task_measures: dict[str, float] = field(default_factory=dict)
    repaired_chunks: list[int] = field(default_factory=list)  # per chunk, where the policy reports repairs


def flatten_observation(task: Task, obs: Mapping[str, np.ndarray], obs_keys: Sequence[str]) -> np.ndarray:
    """Concatenate the low-dim keys (names as in demo files) of a task's env observation into (Do,)."""
    features = task.observations(obs)
    return np.concatenate([features[key] for key in obs_keys])


def run_episode(
    task: Task,
    env,
    source: ActionSource,
    seed: int,
    obs_keys: Sequence[str],
    obs_steps: int,
    max_steps: int,
    render_camera: str | None = None,
    cameras: "RenderSettings | None" = None,
) -> EpisodeResult:
    """Roll out one seeded episode until success or ``max_steps``; exceptions become a failed result.

    Args:
        task: the task `env` runs (`carp.tasks`): it resets, steps, observes, scores and draws the env.
        env: an env built by ``task.make_env``.
        source: decides actions from the observation history.
        seed: reset seed (``task.reset``: the initial state is a function of the seed only).
        obs_keys: low-dim keys concatenated into the observation features, in training order.
        obs_steps: ``To``.
        max_steps: step limit.
        render_camera: when set, a video frame of this camera (``task.video``) is kept after every step.
        cameras: the cameras (and render settings) an image policy sees, rendered after every step into the
            ``images`` history its source receives; None for state policies.
    """
    started = time.perf_counter()
    result = EpisodeResult(seed=seed, success=False, steps=0, seconds=0.0)
    renderer = video = None
    measure = task.measure()

    def observe_cameras() -> np.ndarray:
        rendering_started = time.perf_counter()
        images = renderer.frame()
        result.render_seconds.append(time.perf_counter() - rendering_started)
        return images

    try:
        obs = task.reset(env, seed)
        source.reset(env, seed)
        measure.reset(env)
        history = deque([flatten_observation(task, obs, obs_keys)] * obs_steps, maxlen=obs_steps)
        image_history = None
        if cameras is not None:
            renderer = task.cameras(env, cameras)
            image_history = deque([observe_cameras()] * obs_steps, maxlen=obs_steps)
        if render_camera is not None:
            video = task.video(env, render_camera)
        while result.steps < max_steps and not result.success:
            seen = {} if image_history is None else {"images": np.stack(image_history)}
            actions, timing = source.act(np.stack(history), env, **seen)
            if timing is not None:
                result.prediction_seconds.append(timing.prediction)
                result.decoding_seconds.append(timing.decoding)
                result.encoding_seconds.append(timing.encoding)
                if timing.repaired is not None:
                    result.repaired_chunks.append(timing.repaired)
            for action in actions:
                obs, _ = task.step(env, action)
                history.append(flatten_observation(task, obs, obs_keys))
                if image_history is not None:
                    image_history.append(observe_cameras())
                result.steps += 1
                measure.observe(env, result.steps)
                if video is not None:
                    result.frames.append(video.frame())
                if task.is_success(env):
                    result.success = True
                    break
                if result.steps >= max_steps:
                    break
    except Exception as error:  # noqa: BLE001 - a crash in one episode is a recorded failure, not a dead evaluation
        result.success = False
        result.error = f"{type(error).__name__}: {error}"
        logger.warning("episode with seed %d crashed:\n%s", seed, traceback.format_exc())
    finally:
        for context in (renderer, video):
            if context is not None:
                context.close()
    result.task_measures = measure.values()
    result.seconds = time.perf_counter() - started
    return result


@dataclass(frozen=True)
class EpisodeJob:
    """What a worker needs to run one episode."""

    seed: int
    record_video: bool


# How often an episode is started before a worker death while running it counts as the episode's crash. Twice:
# a death caused by something else (the out-of-memory killer picking the worker) does not cost the episode, while an
# episode that kills its worker every time (it is seeded, so it will) ends after one retry instead of looping.
EPISODE_ATTEMPTS = 2

# Per-process state of a worker: its env and action source, built once by the initializer.
_worker_state: dict = {}


def _init_worker(env_args: dict, source_factory: Callable[[], ActionSource], settings: dict) -> None:
    import torch

    torch.set_num_threads(1)
    task = task_for_env_args(env_args)
    _worker_state["task"] = task
    _worker_state["env"] = task.make_env(env_args)
    _worker_state["source"] = source_factory()
    _worker_state["settings"] = settings


def _run_job(job: EpisodeJob) -> EpisodeResult:
    settings = _worker_state["settings"]
    return run_episode(
        _worker_state["task"],
        _worker_state["env"],
        _worker_state["source"],
        job.seed,
        settings["obs_keys"],
        settings["obs_steps"],
        settings["max_steps"],
        render_camera=settings["video_camera"] if job.record_video else None,
        cameras=settings["cameras"],
    )


class WorkerStartError(RuntimeError):
    """An evaluation worker could not build its env or action source; no episode can run."""


def _worker_main(connection, env_args: dict, source_factory: Callable[[], ActionSource], settings: dict) -> None:
    """A worker process: build env and source, say so, then run each job received until told to stop (None)."""
    try:
        _init_worker(env_args, source_factory, settings)
    except Exception as error:  # noqa: BLE001 - reported to the parent, which stops the evaluation with it
        connection.send(("failed", f"{type(error).__name__}: {error}"))
        return
    connection.send(("ready", None))
    while (job := connection.recv()) is not None:
        connection.send(("result", _run_job(job)))


def exit_reason(exit_code: int | None) -> str:
    """How a worker process ended, from its exit code (negative: the signal that killed it)."""
    if exit_code is not None and exit_code < 0:
        try:
            return f"killed by {signal.Signals(-exit_code).name}"
        except ValueError:
            return f"killed by signal {-exit_code}"
    return f"exited with code {exit_code}"


class _Worker:
    """One spawned worker process, the pipe to it and the job it is running."""

    def __init__(self, context, env_args: dict, source_factory: Callable[[], ActionSource], settings: dict) -> None:
        self.connection, child_end = context.Pipe()
        self.process = context.Process(
            target=_worker_main, args=(child_end, env_args, source_factory, settings), daemon=True
        )
        self.process.start()
        child_end.close()  # only the child holds its end, so the parent reads EOF when the child dies
        self.ready = False
        self.job: EpisodeJob | None = None
        self.job_started = 0.0

    def receive(self) -> tuple[str, object] | None:
        """The worker's next message, or None when it died (its pipe closed)."""
        try:
            return self.connection.recv()
        except (EOFError, OSError):
            return None

    def start_job(self, job: EpisodeJob) -> None:
        self.job, self.job_started = job, time.perf_counter()
        self.connection.send(job)

    def death_reason(self) -> str:
        self.process.join()
        return f"worker {exit_reason(self.process.exitcode)}"

    def stop(self) -> None:
        """Ask an idle worker to exit; kill one that is still busy (the evaluation is being abandoned)."""
        if self.process.is_alive() and self.job is None and self.ready:
            try:
                self.connection.send(None)
            except OSError:
                pass
            self.process.join(timeout=10)
        if self.process.is_alive():
            self.process.kill()
        self.process.join()
        self.connection.close()


def _run_in_workers(
    jobs: Sequence[EpisodeJob],
    env_args: dict,
    source_factory: Callable[[], ActionSource],
    settings: dict,
    workers: int,
    on_result: Callable[[EpisodeResult], None],
) -> None:
    """Run `jobs` on up to `workers` spawned processes, replacing any that dies; each result goes to `on_result`.

    A job whose worker dies is started again (`EPISODE_ATTEMPTS` starts in all), then reported as a crashed episode.

    Raises:
        WorkerStartError: a worker failed or died while building its env and action source.
    """
    # spawn: each worker builds its own MuJoCo context and torch runtime instead of inheriting this process's.
    context = multiprocessing.get_context("spawn")
    pending = deque(jobs)
    attempts = dict.fromkeys((job.seed for job in jobs), 0)
    remaining = len(jobs)
    pool: list[_Worker] = []

    def dispatch() -> None:
        for worker in pool:
            if worker.ready and worker.job is None and pending:
                job = pending.popleft()
                attempts[job.seed] += 1
                worker.start_job(job)
        starting = sum(not worker.ready for worker in pool)
        for _ in range(min(len(pending) - starting, workers - len(pool))):
            pool.append(_Worker(context, env_args, source_factory, settings))

    def bury(worker: _Worker) -> None:
        nonlocal remaining
        reason = worker.death_reason()
        pool.remove(worker)
        worker.connection.close()
        if not worker.ready:
            raise WorkerStartError(f"an evaluation worker {reason.removeprefix('worker ')} while starting")
        job = worker.job
        if job is None:
            return
        if attempts[job.seed] < EPISODE_ATTEMPTS:
            logger.warning("episode with seed %d: %s; running it again in another worker", job.seed, reason)
            pending.appendleft(job)
            return
        logger.warning("episode with seed %d: %s, %d times; recorded as crashed", job.seed, reason, attempts[job.seed])
        seconds = time.perf_counter() - worker.job_started
        on_result(EpisodeResult(job.seed, False, 0, seconds, error=f"{reason} ({attempts[job.seed]} attempts)"))
        remaining -= 1

    try:
        dispatch()
        while remaining > 0:
            wait([worker.connection for worker in pool] + [worker.process.sentinel for worker in pool])
            for worker in list(pool):
                # A message a worker sent before dying is read before its death is handled.
                message = worker.receive() if worker.connection.poll() else None
                if message is None:
                    if not worker.process.is_alive():
                        bury(worker)
                    continue
                kind, payload = message
                if kind == "failed":
                    raise WorkerStartError(f"an evaluation worker could not start: {payload}")
                worker.ready = True
                if kind == "result":
                    worker.job = None
                    on_result(payload)
                    remaining -= 1
            dispatch()
    finally:
        for worker in pool:
            worker.stop()


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
    cameras: "RenderSettings | None" = None,
) -> list[EpisodeResult]:
    """Run one episode per seed across ``workers`` processes (one env each); results in seed order.

    Args:
        env_args: env description (the data's ``env_args``).
        source_factory: picklable zero-argument callable building the action source inside each worker.
        seeds: one episode per seed.
        obs_keys: observation keys in training order.
        obs_steps: ``To``.
        max_steps: step limit per episode.
        workers: processes; 1 runs in this process (where a native crash ends the evaluation itself). With more,
            an episode whose worker dies is run again on a fresh worker, then recorded as crashed (a failure whose
            `error` says how the worker died); see `EPISODE_ATTEMPTS`.
        video_episodes: the first this many seeds keep rendered frames.
        video_camera: camera used for videos.
        description: progress bar label.
        cameras: the cameras an image policy sees (rendered after every step, see :func:`run_episode`); None for
            state policies.

    Raises:
        WorkerStartError: a worker process could not build its env or action source.
    """
    settings = {
        "obs_keys": list(obs_keys),
        "obs_steps": obs_steps,
        "max_steps": max_steps,
        "video_camera": video_camera if video_episodes > 0 else None,
        "cameras": cameras,
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

        def record(result: EpisodeResult) -> None:
            results[result.seed] = result
            progress.update()
            progress.set_postfix(success=_rate(results))

        _run_in_workers(jobs, env_args, source_factory, settings, workers, record)
    progress.close()
    return [results[job.seed] for job in jobs]


def _rate(results: dict[int, EpisodeResult]) -> str:
    return f"{sum(r.success for r in results.values())}/{len(results)}"
