"""Offline checks of a policy: its greedy action chunks against demonstrated ones on held-out windows.

Two uses: the training stages log the held-out errors of every trained policy (`held_out_action_errors`), and the
evaluate stage scores a policy on a task without a simulator (`carp.tasks.offline`) by the same errors in more detail
(`offline_evaluation`): over every held-out window, per action dimension, per row of the chunk (horizon step) and per
held-out episode. Errors are root mean squares in the actions' own units (the task's ``ActionFormat``, as the policy
predicts them), so that families compare on one scale.
"""

from collections.abc import Callable, Sequence

import numpy as np

from carp.data.replay_buffer import ReplayBuffer
from carp.data.windows import window_row_indices

OFFLINE_EPISODE_COLUMNS = ["episode", "steps", "windows", "action_rmse", "executed_action_rmse"]
"""The columns of the per-episode table `offline_evaluation` returns, one row per held-out episode."""


def predicted_chunks(
    policy,
    obs: np.ndarray,
    batch_size: int = 512,
    images: Callable[[np.ndarray], np.ndarray] | None = None,
) -> np.ndarray:
    """The policy's chunks for windows of observations, ``batch_size`` windows per call.

    Args:
        policy: a policy of any family (`carp.policies.base.Policy`).
        obs: (N, To, Do) raw observations.
        batch_size: windows per call.
        images: for an image policy, reads the camera images of windows: (b,) indices into ``obs`` -> (b, To,
            cameras, 3, h, w) uint8 (`carp.data.image_windows.ImageWindowReader.images`); None for state.

    Returns:
        (N, H, A) raw actions.
    """

    def predict(start: int) -> np.ndarray:
        window_indices = np.arange(start, min(start + batch_size, len(obs)))
        seen = {} if images is None else {"images": images(window_indices)}
        return policy.predict_action(obs[window_indices], **seen)

    return np.concatenate([predict(start) for start in range(0, len(obs), batch_size)])


def held_out_action_errors(
    policy,
    obs: np.ndarray,
    actions: np.ndarray,
    obs_steps: int,
    action_steps: int,
    batch_size: int = 512,
    images: Callable[[np.ndarray], np.ndarray] | None = None,
) -> dict[str, float]:
    """RMSE in original action units of the whole chunk and of the executed part ``[To-1 : To-1+Ta]``.

    Args:
        policy: a policy of any family (`carp.policies.base.Policy`).
        obs: (N, To, Do) raw observations.
        actions: (N, H, A) raw demonstrated actions.
        obs_steps: ``To``.
        action_steps: ``Ta``.
        batch_size: windows per call.
        images: see `predicted_chunks`; None for state.
    """
    if len(obs) == 0:
        return {}
    errors = chunk_errors(predicted_chunks(policy, obs, batch_size, images), actions, obs_steps, action_steps)
    return {
        "valid_action_rmse": errors["action_rmse"],
        "valid_executed_action_rmse": errors["executed_action_rmse"],
    }


def chunk_errors(
    predicted: np.ndarray,
    actions: np.ndarray,
    obs_steps: int,
    action_steps: int,
    dimension_names: Sequence[str] = (),
) -> dict[str, float]:
    """Root mean squared errors of predicted chunks against demonstrated ones.

    Args:
        predicted: (N, H, A) predicted raw actions, N >= 1.
        actions: (N, H, A) demonstrated raw actions.
        obs_steps: ``To``; rows ``To-1 .. To-2+Ta`` of a chunk are the ones a robot executes.
        action_steps: ``Ta``.
        dimension_names: names of the A dimensions for the per-dimension keys; empty for none of those keys.

    Returns:
        ``action_rmse`` (every row and dimension), ``executed_action_rmse`` (the executed rows),
        ``step_rmse/<h>`` for each row h = 0 .. H-1 of the chunk (every dimension) and, with names,
        ``dimension_rmse/<name>`` for each dimension (every row).
    """
    if predicted.shape != actions.shape or predicted.ndim != 3 or len(predicted) == 0:
        raise ValueError(f"predicted {predicted.shape} and demonstrated {actions.shape} chunks must be (N, H, A), N>0")
    if dimension_names and len(dimension_names) != actions.shape[2]:
        raise ValueError(f"{len(dimension_names)} dimension names for {actions.shape[2]} action dimensions")
    squared = (np.asarray(predicted, dtype=np.float64) - actions) ** 2  # (N, H, A)
    executed = squared[:, obs_steps - 1 : obs_steps - 1 + action_steps]
    errors = {
        "action_rmse": float(np.sqrt(squared.mean())),
        "executed_action_rmse": float(np.sqrt(executed.mean())),
    }
    per_step = np.sqrt(squared.mean(axis=(0, 2)))  # (H,)
    errors |= {f"step_rmse/{step}": float(value) for step, value in enumerate(per_step)}
    per_dimension = np.sqrt(squared.mean(axis=(0, 1)))  # (A,)
    errors |= {f"dimension_rmse/{name}": float(value) for name, value in zip(dimension_names, per_dimension)}
    return errors


def offline_evaluation(
    policy,
    buffer: ReplayBuffer,
    horizon: int,
    obs_steps: int,
    action_steps: int,
    dimension_names: Sequence[str],
    batch_size: int = 512,
) -> tuple[dict[str, float], list[dict[str, float]]]:
    """A policy's action errors on the held-out episodes of a replay buffer, as a task without a simulator is scored.

    Every window of a held-out episode counts once (the windows of `carp.data.windows`, the training windows'
    padding at the episode's ends included), so the overall errors weigh each step of every episode alike.

    Args:
        policy: a state policy of any family (`carp.policies.base.Policy`), its task selected.
        buffer: the task's replay buffer (`carp.data.replay_buffer`); its ``valid_episodes`` are scored.
        horizon: ``H``.
        obs_steps: ``To``.
        action_steps: ``Ta``.
        dimension_names: the A action dimensions' names (`carp.tasks.base.ActionFormat.dimension_names`).
        batch_size: windows per call.

    Returns:
        The summary (`chunk_errors` over every held-out window, with ``held_out_episodes`` and
        ``held_out_windows``) and one row per held-out episode (`OFFLINE_EPISODE_COLUMNS`).

    Raises:
        ValueError: no episode is held out.
    """
    held_out = np.flatnonzero(buffer.valid_episodes)
    if len(held_out) == 0:
        raise ValueError(
            "no held-out episode to score: the demos need a 'valid' split (LeRobotDataset) or mask, or "
            "data.valid_fraction > 0 with two episodes or more"
        )
    predictions, demonstrations, rows = [], [], []
    for episode in held_out:
        window_rows = window_row_indices(buffer.episode_ends, horizon, obs_steps - 1, action_steps - 1, [episode])
        demonstrated = buffer.action[window_rows]  # (n, H, A)
        predicted = predicted_chunks(policy, buffer.obs[window_rows[:, :obs_steps]], batch_size)
        errors = chunk_errors(predicted, demonstrated, obs_steps, action_steps)
        rows.append(
            {
                "episode": int(episode),
                "steps": int(buffer.episode_ends[episode] - buffer.episode_starts[episode]),
                "windows": len(window_rows),
                "action_rmse": errors["action_rmse"],
                "executed_action_rmse": errors["executed_action_rmse"],
            }
        )
        predictions.append(predicted)
        demonstrations.append(demonstrated)
    predicted, demonstrated = np.concatenate(predictions), np.concatenate(demonstrations)
    summary = chunk_errors(predicted, demonstrated, obs_steps, action_steps, dimension_names)
    summary |= {"held_out_episodes": len(held_out), "held_out_windows": len(predicted)}
    return summary, rows
