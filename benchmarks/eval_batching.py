"""Evaluation throughput: one policy per worker process vs one policy batched across the workers' environments.

The evaluate stage runs episodes in `eval.workers` processes, one env each. Two ways to place the policy:
- per worker (what `carp.evaluation.runner.evaluate_policy` does): each worker loads the checkpoint and predicts for
  its own env at batch 1 on one thread;
- batched: the workers only step their envs; this process gathers the observation histories of all workers, predicts
  one (W, H, A) batch on one thread and sends each worker its actions.

Both run the same seeds with the same checkpoint, episode limit and success check; the table reports simulator steps
per second (the work done, independent of how many episodes succeed), episodes per minute and the success count.

Usage: python benchmarks/eval_batching.py --checkpoint models/policy/lift/carp/seed0/policy.pt
       --processed data/processed/lift [--workers 2] [--episodes 6] [--max-steps 200] [--repeats 2]
"""

import argparse
import functools
import multiprocessing
import os
import time
from collections import deque
from pathlib import Path

import numpy as np
import torch

from carp.data.dataset import load_task_windows
from carp.evaluation.rollout import evaluate_episodes, flatten_observation
from carp.evaluation.sources import PolicySource, executed_actions
from carp.policies.registry import load_policy
from carp.tasks import task_for_env_args
from carp.tasks.base import ActionFormat

OBS_KEYS = ["object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos"]
OBS_STEPS, ACTION_HORIZON, ACTION_STEPS = 2, 16, 8


def env_worker(connection, env_args: dict, max_steps: int) -> None:
    """Serve one env: `("reset", seed)` -> history; `("step", actions)` -> (history, steps, finished, success)."""
    torch.set_num_threads(1)
    task = task_for_env_args(env_args)
    env = task.make_env(env_args)
    history: deque = deque(maxlen=OBS_STEPS)
    steps = 0
    while True:
        command, argument = connection.recv()
        if command == "close":
            return
        if command == "reset":
            observation = flatten_observation(task, task.reset(env, argument), OBS_KEYS)
            history.extend([observation] * OBS_STEPS)
            steps = 0
            connection.send(np.stack(history))
            continue
        success = False
        for action in argument:
            observation, _ = task.step(env, action)
            history.append(flatten_observation(task, observation, OBS_KEYS))
            steps += 1
            success = task.is_success(env)
            if success or steps >= max_steps:
                break
        connection.send((np.stack(history), steps, success or steps >= max_steps, success))


def run_batched(
    checkpoint: Path, env_args: dict, action_format: ActionFormat, seeds: list[int], workers: int, max_steps: int
):
    """Episodes per seed with one batched policy in this process; returns (total steps, successes)."""
    torch.set_num_threads(1)
    policy = load_policy(checkpoint)
    context = multiprocessing.get_context("spawn")
    connections, processes = [], []
    for _ in range(workers):
        parent, child = context.Pipe()
        process = context.Process(target=env_worker, args=(child, env_args, max_steps), daemon=True)
        process.start()
        connections.append(parent)
        processes.append(process)
    pending = list(seeds)
    histories: dict[int, np.ndarray] = {}
    total_steps = successes = 0
    for index, connection in enumerate(connections):
        if pending:
            connection.send(("reset", pending.pop(0)))
            histories[index] = connection.recv()
    while histories:
        active = sorted(histories)
        chunks = policy.predict_action(np.stack([histories[index] for index in active]))  # (W, H, A)
        for index, chunk in zip(active, chunks, strict=True):
            connections[index].send(("step", executed_actions(chunk, OBS_STEPS, ACTION_STEPS, action_format)))
        for index in active:
            history, steps, finished, success = connections[index].recv()
            histories[index] = history
            if finished:
                total_steps += steps
                successes += int(success)
                del histories[index]
                if pending:
                    connections[index].send(("reset", pending.pop(0)))
                    histories[index] = connections[index].recv()
    for connection, process in zip(connections, processes, strict=True):
        connection.send(("close", None))
        process.join()
    return total_steps, successes


def run_per_worker(
    checkpoint: Path, env_args: dict, action_format: ActionFormat, seeds: list[int], workers: int, max_steps: int
):
    """The evaluate stage's own path: a policy in every worker; returns (total steps, successes)."""
    factory = PolicySourceFactory(checkpoint, action_format)
    results = evaluate_episodes(env_args, factory, seeds, OBS_KEYS, OBS_STEPS, max_steps, workers=workers)
    return sum(result.steps for result in results), sum(result.success for result in results)


class PolicySourceFactory:
    """Picklable zero-argument factory for the worker processes."""

    def __init__(self, checkpoint: Path, action_format: ActionFormat) -> None:
        self.checkpoint = checkpoint
        self.action_format = action_format

    def __call__(self) -> PolicySource:
        return PolicySource(
            functools.partial(load_policy, self.checkpoint), self.action_format, OBS_STEPS, ACTION_STEPS
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=Path, default=Path("models/policy/lift/carp/seed0/policy.pt"))
    parser.add_argument("--processed", type=Path, default=Path("data/processed/lift"), help="for the env_args")
    parser.add_argument("--controller", default="absolute")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--episodes", type=int, default=6)
    parser.add_argument("--max-steps", type=int, default=200)
    parser.add_argument("--seed", type=int, default=100000)
    parser.add_argument("--repeats", type=int, default=2, help="alternating runs of each mode")
    args = parser.parse_args()

    windows = load_task_windows(args.processed, ACTION_HORIZON, OBS_STEPS, ACTION_STEPS)
    env_args = windows.buffer.attrs["env_args"]
    action_format = task_for_env_args(env_args).action_format(args.controller)
    seeds = [args.seed + index for index in range(args.episodes)]
    modes = {"policy per worker": run_per_worker, "policy batched across workers": run_batched}
    rows = []
    for repeat in range(args.repeats):
        for name, run in modes.items():
            started = time.perf_counter()
            steps, successes = run(args.checkpoint, env_args, action_format, seeds, args.workers, args.max_steps)
            seconds = time.perf_counter() - started
            rows.append((name, repeat + 1, steps, successes, steps / seconds, 60 * len(seeds) / seconds))

    print(f"evaluation throughput, {args.workers} workers, {len(seeds)} episodes of at most {args.max_steps} steps")
    print(f"| {'mode':<30} | run | env steps | successes | steps/s | episodes/min |")
    print(f"|{'-' * 32}|-----|-----------|-----------|---------|--------------|")
    for name, repeat, steps, successes, steps_per_second, episodes_per_minute in rows:
        print(
            f"| {name:<30} | {repeat:>3} | {steps:>9} | {successes:>9} | {steps_per_second:>7.1f} | "
            f"{episodes_per_minute:>12.2f} |"
        )


if __name__ == "__main__":
    main()
