"""Collect scripted-expert demonstrations of any task (`carp.tasks`) into a robomimic-schema HDF5 file.

Episodes run over consecutive seeds ``seed, seed + 1, ...``; each episode ends at the step where the task's success
check first fires (as in robomimic's human demonstrations) or after ``max_steps`` (at most the task's step limit).
Only successful episodes are kept. Every step stores the observation *before* the action, so a demo of T actions has
T observations.
"""

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from carp.data.robomimic_io import Episode, write_demonstrations
from carp.tasks import get_task
from carp.tasks.base import Task

logger = logging.getLogger(__name__)


class CollectionError(RuntimeError):
    """The expert cannot deliver the requested number of successful demonstrations."""


@dataclass(frozen=True)
class CollectionSummary:
    """Outcome of one collection run.

    Attributes:
        task: short task name.
        kept: successful episodes written.
        attempted: episodes run.
        success_rate: kept / attempted.
        seeds: reset seeds of the kept episodes, in file order.
        seconds: wall-clock time of the run.
    """

    task: str
    kept: int
    attempted: int
    success_rate: float
    seeds: list[int]
    seconds: float


def run_expert_episode(task: Task, env, seed: int, max_steps: int) -> tuple[Episode, bool]:
    """Run one seeded episode of the task's expert, stopping at the first success.

    Returns:
        The episode (obs key -> (T, Do_key), actions (T, stored action width), states (T, S), rewards (T,),
        dones (T,); attrs hold the seed) and whether it succeeded.
    """
    obs = task.reset(env, seed)
    expert = task.make_expert(env, seed)
    observations: dict[str, list[np.ndarray]] = {}
    actions, states, rewards = [], [], []
    success = False
    for _ in range(max_steps):
        for key, value in task.observations(obs).items():
            observations.setdefault(key, []).append(value)
        states.append(task.simulator_state(env))
        action = expert.act()
        actions.append(action)
        obs, reward = task.step(env, action)
        rewards.append(reward)
        if task.is_success(env):
            success = True
            break
    dones = np.zeros(len(actions), dtype=np.int64)
    dones[-1] = int(success)
    episode = Episode(
        obs={key: np.stack(values) for key, values in observations.items()},
        actions=np.stack(actions),
        states=np.stack(states),
        rewards=np.asarray(rewards),
        dones=dones,
        attrs={"seed": int(seed)},
    )
    return episode, success


def collect_demonstrations(
    task: str,
    num_demos: int,
    output_path: Path,
    seed: int,
    controller: str = "absolute",
    max_steps: int = 400,
    max_attempts: int | None = None,
    staging_dir: Path | None = None,
) -> CollectionSummary:
    """Run the task's scripted expert until ``num_demos`` episodes succeed and write them to ``output_path``.

    Args:
        task: a registered task name (`carp.tasks.TASK_NAMES`).
        num_demos: successful episodes to keep.
        output_path: destination ``.hdf5`` (written atomically, only once collection is complete).
        seed: first reset seed; episodes use ``seed, seed + 1, ...``. Keep these disjoint from evaluation seeds.
        controller: ``"absolute"`` or ``"delta"`` arm input (Push-T: ``"absolute"`` only).
        max_steps: step limit per episode; a task's own step limit (Push-T: 300) caps it.
        max_attempts: episode budget; defaults to ``3 * num_demos``.
        staging_dir: where the file is built before its rename (see :mod:`carp.data.staging`); ``None`` uses
            ``output_path``'s folder.

    Raises:
        ValueError: unknown task or controller, or non-positive counts.
        CollectionError: the remaining budget can no longer reach ``num_demos`` successes.
    """
    if num_demos < 1:
        raise ValueError(f"num_demos must be positive, got {num_demos}")
    max_attempts = 3 * num_demos if max_attempts is None else max_attempts
    if max_attempts < num_demos:
        raise ValueError(f"max_attempts ({max_attempts}) must be at least num_demos ({num_demos})")
    task_name, task = task, get_task(task)
    if task.step_limit is not None:
        max_steps = min(max_steps, task.step_limit)
    env_args = task.make_env_args(controller)
    env = task.make_env(env_args)
    started = time.perf_counter()
    episodes: list[Episode] = []
    failed_seeds: list[int] = []
    attempted = 0
    try:
        with tqdm(total=num_demos, desc=f"collect {task_name}", unit="demo") as progress:
            while len(episodes) < num_demos:
                if len(episodes) + (max_attempts - attempted) < num_demos:
                    raise CollectionError(
                        f"{task_name}: expert succeeded on {len(episodes)} of {attempted} episodes "
                        f"({len(episodes) / attempted:.0%}); {num_demos} demos cannot be reached within "
                        f"max_attempts={max_attempts} (failed seeds: {failed_seeds})"
                    )
                episode_seed = seed + attempted
                episode, success = run_expert_episode(task, env, episode_seed, max_steps)
                attempted += 1
                if success:
                    episodes.append(episode)
                    progress.update(1)
                else:
                    failed_seeds.append(episode_seed)
                    logger.warning("%s: expert failed on seed %d within %d steps", task_name, episode_seed, max_steps)
                progress.set_postfix(attempted=attempted)
    finally:
        env.close()
    kept_seeds = [int(episode.attrs["seed"]) for episode in episodes]
    success_rate = len(episodes) / attempted
    file_attrs = {
        "task": task_name,
        "expert": task.expert_name,
        "controller": controller,
        "success_rate": success_rate,
        "attempted": attempted,
        "kept": len(episodes),
        "seeds": kept_seeds,
        "failed_seeds": failed_seeds,
        "first_seed": seed,
        "max_steps": max_steps,
        **task.versions(),
    }
    write_demonstrations(output_path, episodes, env_args, file_attrs, staging_dir=staging_dir)
    seconds = time.perf_counter() - started
    logger.info(
        "%s: kept %d of %d episodes (%.0f%%), mean %.1f steps, %.1f s -> %s",
        task_name,
        len(episodes),
        attempted,
        100 * success_rate,
        np.mean([episode.length for episode in episodes]),
        seconds,
        output_path,
    )
    return CollectionSummary(
        task=task_name,
        kept=len(episodes),
        attempted=attempted,
        success_rate=success_rate,
        seeds=kept_seeds,
        seconds=seconds,
    )
