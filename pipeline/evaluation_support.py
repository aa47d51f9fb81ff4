"""The evaluate stage's episode runner, shared with the duel: a checkpoint on a task's seeds, as `evaluate` runs it.

Apart from `stage_support` so that only the scripts that roll out policies reach the evaluation code.
"""

import os
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from stage_support import camera_settings

from carp.config import Params


def episode_runner(
    params: Params,
    task: str,
    family: str,
    env_args: dict,
    video_seeds: list[int] | None = None,
) -> Callable[[Path, list[int]], tuple[dict, list]]:
    """Runs a checkpoint of `family` on `task`'s episode seeds as the evaluate stage does: (checkpoint, seeds) ->
    (summary, episodes) of `carp.evaluation.runner.evaluate_policy`.

    `env_args` are the task's environment arguments (its replay buffer's ``env_args``); episodes on exactly
    `video_seeds` are recorded when ``eval.video`` is on.
    """
    from carp.evaluation.runner import EvaluationSetup, evaluate_policy

    config = params.eval
    workers = config.workers or os.cpu_count() or 1
    setup = EvaluationSetup(
        env_args=env_args,
        action_format=params.action_format,
        obs_keys=params.obs_keys_for(task),
        obs_steps=params.data.obs_steps,
        action_steps=params.data.action_steps,
        max_steps=params.max_steps_for(task),
        inference=params.inference_settings(family, task),
        backend=config.backend,
        cameras=camera_settings(params),
        task=task,
        ensemble_m=config.ensemble_m,
    )

    def run_episodes(checkpoint: Path, seeds: list[int]) -> tuple[dict, list]:
        videos = config.video_episodes if config.video and seeds == video_seeds else 0
        return evaluate_policy(checkpoint, seeds, replace(setup, workers=min(workers, len(seeds))), videos)

    return run_episodes
