"""Action sources for the rollout loop: the trained CARP policy and the scripted experts."""

import time
from pathlib import Path

import numpy as np
import torch

from carp.data.rotation import rot6d_to_absolute_actions
from carp.evaluation.onnx_policy import OnnxPolicy
from carp.evaluation.rollout import ChunkTiming
from carp.policy.policy import CarpPolicy


def executed_actions(chunk: np.ndarray, obs_steps: int, action_steps: int, controller: str) -> np.ndarray:
    """The part of a predicted chunk the env executes, in the controller's action format.

    Args:
        chunk: (H, A) raw actions predicted from observations at steps ``t - To + 1 .. t``; row ``To - 1`` is step t.
        obs_steps: ``To``.
        action_steps: ``Ta``.
        controller: ``absolute`` converts 10-D (position, 6-D rotation, gripper) rows to the controller's 7-D form.

    Returns:
        (Ta, 7 or A) float64.
    """
    executed = np.asarray(chunk[obs_steps - 1 : obs_steps - 1 + action_steps], dtype=np.float64)
    if controller == "absolute":
        executed = rot6d_to_absolute_actions(executed)
    return executed


class ExpertSource:
    """A scripted expert (privileged state) behind the same interface as the policy; one action per decision."""

    def __init__(self, task: str) -> None:
        self.task = task
        self._expert = None

    def reset(self, env, seed: int) -> None:
        """Bind a fresh expert to the just-reset env."""
        from carp.data.experts import make_expert

        self._expert = make_expert(self.task, env)
        self._expert.reset()

    def act(self, observation_history: np.ndarray, env) -> tuple[np.ndarray, None]:
        """(1, 7) the expert's next action."""
        return self._expert.act()[None, :], None


class PolicySource:
    """A trained policy checkpoint: predicts ``H`` actions, executes ``actions[To-1 : To-1+Ta]``.

    Args:
        checkpoint_path: self-contained policy checkpoint (``models/policy/policy.pt``).
        controller: ``absolute`` converts the 10-D actions back to the controller's 7-D form.
        top_k: 1 = greedy; >1 samples from the top-k tokens with a generator seeded per episode.
        task_index: task id for multi-task policies.
        device: torch device for inference.
        onnx_directory: graphs written by `carp.evaluation.onnx_policy.export_policy_graphs` for this checkpoint
            and this `top_k`; when given, chunks are predicted by ONNX Runtime instead of PyTorch.
    """

    def __init__(
        self,
        checkpoint_path: Path,
        controller: str,
        obs_steps: int,
        action_steps: int,
        top_k: int = 1,
        task_index: int | None = None,
        device: str = "cpu",
        onnx_directory: Path | None = None,
    ) -> None:
        self.policy = (
            OnnxPolicy(onnx_directory)
            if onnx_directory is not None
            else CarpPolicy.load(Path(checkpoint_path), map_location=device)
        )
        if isinstance(self.policy, OnnxPolicy) and self.policy.top_k != top_k:
            raise ValueError(
                f"the ONNX graphs in {onnx_directory} use top_k = {self.policy.top_k}, got top_k = {top_k}"
            )
        self.controller = controller
        self.obs_steps = obs_steps
        self.action_steps = action_steps
        self.top_k = top_k
        self.task_index = task_index
        self.device = torch.device(device)
        self._generator = torch.Generator(device=self.device)

    def reset(self, env, seed: int) -> None:
        """New episode: seed sampling with the episode's seed.

        An episode's draws then do not depend on which worker runs it or on what that worker ran before.
        """
        self._generator.manual_seed(seed)

    def act(self, observation_history: np.ndarray, env) -> tuple[np.ndarray, ChunkTiming]:
        """(Ta, 7 or A) actions for the env and the chunk's prediction/decoding time."""
        if isinstance(self.policy, CarpPolicy):
            timed = self.policy.predict_action_timed(
                observation_history[None], task_index=self.task_index, top_k=self.top_k, generator=self._generator
            )
        else:
            timed = self.policy.predict_action_timed(
                observation_history[None], task_index=self.task_index, generator=self._generator
            )
        actions, prediction_seconds, decoding_seconds = timed
        started = time.perf_counter()
        executed = executed_actions(actions[0], self.obs_steps, self.action_steps, self.controller)
        decoding_seconds += time.perf_counter() - started
        return executed, ChunkTiming(prediction=prediction_seconds, decoding=decoding_seconds)
