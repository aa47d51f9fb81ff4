"""A robosuite arm task's scripted expert: success rate and time per episode over a range of reset seeds.

Each episode is run the way `collect` runs it (`carp.data.collect.run_expert_episode`): a seeded reset, then the
expert's actions until the task's success check fires or the step limit passes. The table reports the successes, the
wall time per episode (expert and simulation together, on whatever load the machine has), the control steps per
successful episode and the failed seeds.

Usage: python benchmarks/arm_expert.py --task stack [--controller absolute] [--episodes 50] [--first-seed 1000]
"""

import argparse
import sys
import time

import numpy as np
from tqdm import tqdm

from carp.data.collect import run_expert_episode
from carp.tasks import TASK_NAMES, get_task


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", required=True, help="a registered arm task, e.g. stack")
    parser.add_argument("--controller", default="absolute", help="absolute or delta")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument(
        "--first-seed", type=int, default=1000, help="episodes use seeds first-seed, first-seed + 1, ..."
    )
    parser.add_argument("--max-steps", type=int, default=None, help="step limit; default: the task's evaluation limit")
    arguments = parser.parse_args()
    if arguments.task not in TASK_NAMES:
        print(f"error: --task {arguments.task!r}: expected one of {list(TASK_NAMES)}", file=sys.stderr)
        sys.exit(2)
    task = get_task(arguments.task)
    try:
        env_args = task.make_env_args(arguments.controller)
    except ValueError as error:
        print(f"error: --controller {arguments.controller!r}: {error}", file=sys.stderr)
        sys.exit(2)
    max_steps = arguments.max_steps or task.default_max_steps

    env = task.make_env(env_args)
    seconds, steps, failed_seeds = [], [], []
    seeds = range(arguments.first_seed, arguments.first_seed + arguments.episodes)
    try:
        for seed in tqdm(seeds, desc=f"{arguments.task} {arguments.controller}"):
            started = time.perf_counter()
            episode, success = run_expert_episode(task, env, seed, max_steps)
            seconds.append(time.perf_counter() - started)
            if success:
                steps.append(episode.length)
            else:
                failed_seeds.append(seed)
    finally:
        env.close()

    print(f"{arguments.task}, {arguments.controller} actions, seeds {seeds.start}..{seeds.stop - 1}, limit {max_steps}")
    print(f"{'successes':<24}{len(steps)} / {arguments.episodes}")
    print(f"{'seconds per episode':<24}mean {np.mean(seconds):.2f}, max {np.max(seconds):.2f}")
    if steps:
        print(f"{'steps per success':<24}mean {np.mean(steps):.1f}, max {np.max(steps)}")
    print(f"{'failed seeds':<24}{failed_seeds or 'none'}")


if __name__ == "__main__":
    main()
