"""A robot's control loop against `carp serve`, with carp's own Lift simulator standing in for the robot.

The server runs in this process (`ServerThread`) on a checkpoint (`--checkpoint`, one that records its serving
protocol) or on a randomly initialized tiny CARP policy (`tests/serving/random_policy.py`). The loop talks to it
only through the robot-side client (`carp_client`): every control step it sends the step's observation, one array per
key, asking for a chunk when the `ChunkScheduler` has no action for the step (every `Ta` steps, as carp's evaluation
executes a chunk) and sending the other steps as observations only, so the server's history holds the last `To` steps.
With `--ensemble-m` it asks at every step and executes ACT's temporal ensemble of the overlapping chunks instead.

With `--compare` the same seeds also run in-process (`carp.evaluation.rollout.run_episode` with a `PolicySource` of
the same checkpoint and inference settings) and the executed actions are compared: plain execution reproduces the
evaluation bit for bit with the PyTorch policy.

A checkpoint trained before checkpoints recorded their protocol runs with `--params`, the params it was trained
with (as `carp serve --params`); `--backend onnxruntime` serves CARP's exported graphs, as evaluation runs them by
default. The last line counts the successes.

Usage: PYTHONPATH=src:clients/python python examples/serve_control_loop.py [--checkpoint policy.pt]
       [--params params.yaml] [--backend torch] [--episodes 2] [--seed 100000] [--max-steps 100] [--top-k 3]
       [--ensemble-m 0.01] [--compare]
"""

import argparse
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for folder in (ROOT, ROOT / "src", ROOT / "clients" / "python"):
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))

from carp_client import ChunkScheduler, PolicyClient  # noqa: E402


@dataclass
class LoopEpisode:
    """One episode of the served control loop.

    Attributes:
        seed: the reset seed.
        actions: (steps, stored_dim) float64 actions executed, in the env's format.
        success: whether the task succeeded.
        chunks: chunks requested.
        latencies_ms: the server's inference time of each chunk.
    """

    seed: int
    actions: np.ndarray
    success: bool
    chunks: int = 0
    latencies_ms: list[float] = field(default_factory=list)


def run_served_episode(
    client: PolicyClient, scheduler: ChunkScheduler, task, env, seed: int, action_format, max_steps: int
) -> LoopEpisode:
    """Run one seeded episode of `task` in `env`, its actions from the server `client` is connected to.

    Args:
        client: a connected client; its server's metadata lists the observation keys.
        scheduler: turns the replies' chunks into one action per step; plain (asks every `Ta` steps) or
            ensembling (asks every step).
        task: a `carp.tasks` task (reset, step, observations, success).
        env: an env built by `task.make_env`.
        seed: the reset seed, also the seed of the episode's draws on the server.
        action_format: maps a policy action (A,) to the env's (`carp.tasks.base.ActionFormat.to_env`).
        max_steps: step limit.
    """
    keys = list(client.metadata["observation_keys"])
    # A spec without per-key widths (a checkpoint older than the recorded protocol) takes the concatenated `obs`.
    concatenated = list(client.metadata["observation"]["obs"]["keys"]) if not keys else None
    client.reset(seed)
    scheduler.reset()
    observation = task.reset(env, seed)
    actions, chunks, latencies = [], 0, []
    success = False
    for step in range(max_steps):
        features = task.observations(observation)
        if concatenated is None:
            request = {key: np.asarray(features[key], dtype=np.float32) for key in keys}
        else:
            request = {"obs": np.concatenate([np.asarray(features[key], np.float32).ravel() for key in concatenated])}
        request["step"] = step
        if scheduler.ensemble_m is not None or not scheduler.has_action(step):
            reply = client.infer(request)
            scheduler.add(reply["actions"], reply["step"])
            chunks += 1
            latencies.append(reply["timing_ms"]["inference"])
        else:
            client.observe(request)
        action = scheduler.action(step)  # (A,) float32, the policy's format
        executed = action_format.to_env(np.asarray(action, dtype=np.float64)[None])[0]
        actions.append(executed)
        observation, _ = task.step(env, executed)
        if task.is_success(env):
            success = True
            break
    return LoopEpisode(seed, np.stack(actions), success, chunks, latencies)


class RecordingSource:
    """Wraps an action source and keeps every action it returns (the in-process side of the comparison)."""

    def __init__(self, source) -> None:
        self.source = source
        self.actions: list[np.ndarray] = []

    def reset(self, env, seed: int) -> None:
        """A new episode: forget the recorded actions."""
        self.actions = []
        self.source.reset(env, seed)

    def act(self, history, env, **seen):
        """The wrapped source's actions, recorded."""
        actions, timing = self.source.act(history, env, **seen)
        self.actions.extend(actions)
        return actions, timing


def in_process_episode(checkpoint: Path, inference: dict, task, env, seed: int, spec, action_format, max_steps: int):
    """The same episode through carp's evaluation loop: (executed actions (steps, stored_dim), success)."""
    from carp.evaluation.rollout import run_episode
    from carp.evaluation.sources import PolicySource
    from carp.policies.registry import load_policy

    source = RecordingSource(
        PolicySource(lambda: load_policy(checkpoint), action_format, spec.obs_steps, spec.action_steps, inference)
    )
    result = run_episode(task, env, source, seed, spec.obs_keys, spec.obs_steps, max_steps)
    if result.error:
        raise RuntimeError(f"the in-process episode with seed {seed} crashed: {result.error}")
    return np.stack(source.actions[: result.steps]), result.success


def controller_for(task, action_dim: int) -> str:
    """The controller (`data.controller`) whose policy actions are `action_dim` wide for `task`."""
    from carp.config import CONTROLLERS

    for controller in CONTROLLERS:
        try:
            if task.action_format(controller).policy_dim == action_dim:
                return controller
        except ValueError:  # a controller the task does not support
            continue
    raise ValueError(f"{task.name} has no controller with {action_dim}-D policy actions")


def start_server(checkpoint: Path, params=None, backend: str = "torch"):
    """A `ServerThread` serving `checkpoint` on a free loopback port (`params` and `backend` as `load_served_model`)."""
    from carp.serving.server import PolicyServer, ServerSettings, ServerThread
    from carp.serving.startup import load_served_model

    model, spec = load_served_model(checkpoint, params, backend=backend)
    return ServerThread(PolicyServer(model, spec, ServerSettings(port=0))).start(), model, spec


def main() -> int:
    """Parse the arguments, serve, run the episodes and print one line each."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", type=Path, help="a policy.pt recording its protocol (default: a tiny one)")
    parser.add_argument("--params", type=Path, help="params.yaml whose inference (and, if needed, data) settings apply")
    parser.add_argument("--backend", choices=("torch", "onnxruntime"), default="torch", help="what predicts")
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--seed", type=int, default=100000, help="first episode's seed")
    parser.add_argument("--max-steps", type=int, default=100)
    parser.add_argument("--top-k", type=int, default=None, help="CARP's top_k (default: the family's default)")
    parser.add_argument("--ensemble-m", type=float, default=None, help="temporal ensembling, ACT's weight m")
    parser.add_argument("--compare", action="store_true", help="also run the in-process evaluation loop")
    args = parser.parse_args()

    import dataclasses

    from carp.config import ConfigError, Params, load_params
    from carp.policies.carp.config import CarpInference
    from carp.serving.startup import ServingStartError
    from carp.tasks import get_task
    from tests.serving.random_policy import random_lift_policy

    with tempfile.TemporaryDirectory() as folder:
        checkpoint = args.checkpoint
        if checkpoint is None:
            checkpoint = Path(folder) / "policy.pt"
            random_lift_policy().save(checkpoint)
        try:
            params = load_params(args.params) if args.params is not None else None
            if args.top_k is not None:
                params = params or Params()
                inference = {**params.inference, "carp": CarpInference(top_k=args.top_k)}
                params = dataclasses.replace(params, inference=inference)
            server, model, spec = start_server(checkpoint, params, args.backend)
        except (ServingStartError, ConfigError, ValueError) as error:
            print(f"error: {error}", file=sys.stderr)
            return 1
        task = get_task(model.policy.metadata["task"])
        controller = controller_for(task, spec.action_dim)
        action_format = task.action_format(controller)
        env = task.make_env(task.make_env_args(controller))
        successes = 0
        try:
            with PolicyClient(server.url) as client:
                for index in range(args.episodes):
                    seed = args.seed + index
                    scheduler = ChunkScheduler.from_metadata(client.metadata, args.ensemble_m)
                    served = run_served_episode(client, scheduler, task, env, seed, action_format, args.max_steps)
                    line = (
                        f"seed {seed}: {len(served.actions)} steps, success {served.success}, {served.chunks} chunks, "
                        f"median inference {np.median(served.latencies_ms):.2f} ms"
                    )
                    if args.compare:
                        actions, success = in_process_episode(
                            checkpoint, model.inference, task, env, seed, spec, action_format, args.max_steps
                        )
                        same = actions.shape == served.actions.shape and np.array_equal(actions, served.actions)
                        line += f"; in-process: success {success}, identical actions {same}"
                    print(line, flush=True)
                    successes += served.success
        finally:
            env.close()
            server.stop()
    print(f"{successes}/{args.episodes} episodes succeeded ({model.backend}, {model.policy.description})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
