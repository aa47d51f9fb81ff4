"""Offline checks of a policy: its greedy action chunks against demonstrated ones on held-out windows."""

from collections.abc import Callable

import numpy as np


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
        images: for an image policy, reads the camera images of windows: (b,) indices into ``obs`` -> (b, To,
            cameras, 3, h, w) uint8 (`carp.data.image_windows.ImageWindowReader.images`); None for state.
    """
    if len(obs) == 0:
        return {}

    def predict(start: int) -> np.ndarray:
        window_indices = np.arange(start, min(start + batch_size, len(obs)))
        seen = {} if images is None else {"images": images(window_indices)}
        return policy.predict_action(obs[window_indices], **seen)

    predicted = np.concatenate([predict(start) for start in range(0, len(obs), batch_size)])  # (N, H, A)
    error = predicted - actions
    executed = error[:, obs_steps - 1 : obs_steps - 1 + action_steps]
    return {
        "valid_action_rmse": float(np.sqrt(np.mean(error**2))),
        "valid_executed_action_rmse": float(np.sqrt(np.mean(executed**2))),
    }
