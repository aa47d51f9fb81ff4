"""Evaluate a policy checkpoint in simulation: parallel seeded episodes, summary metrics, batched latency, videos."""

import functools
import logging
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from carp.config import EVAL_BACKENDS
from carp.evaluation.metrics import latency_summary, summarize_episodes
from carp.evaluation.onnx_policy import export_policy_graphs
from carp.evaluation.rollout import EpisodeResult, evaluate_episodes
from carp.evaluation.scratch import scratch_directory
from carp.evaluation.sources import PolicySource
from carp.policy.policy import CarpPolicy

logger = logging.getLogger(__name__)


def evaluate_policy(
    checkpoint_path: Path,
    env_args: dict,
    controller: str,
    obs_keys: Sequence[str],
    obs_steps: int,
    action_steps: int,
    seeds: Sequence[int],
    max_steps: int,
    workers: int,
    top_k: int = 1,
    video_episodes: int = 0,
    task_index: int | None = None,
    backend: str = "onnxruntime",
) -> tuple[dict[str, float], list[EpisodeResult]]:
    """Run one episode per seed with the checkpoint's policy; returns the summary metrics (with `top_k`), episodes.

    Each worker process loads the checkpoint once and runs its policy on one CPU thread. Measured against one policy
    batched across the workers' envs (`benchmarks/eval_batching.py`, 2 workers, 8 Lift episodes, 2 alternating runs
    each): 25.4 and 25.4 simulator steps/s per worker against 24.2 and 23.6 batched, with identical episodes. Per
    chunk the policy needs a few ms against ~8 simulator steps, so batching saves little and adds a round trip
    between processes on every decision.

    With `backend` "onnxruntime" the checkpoint is exported once (greedy or top-k, as `top_k` says) to ONNX graphs in
    a temporary directory that every worker runs with ONNX Runtime (`carp.evaluation.onnx_policy`); otherwise the
    workers run the PyTorch policy. Both choose the same tokens: top-k draws come from a generator seeded with the
    episode's seed either way. The directory does not outlive a killed evaluation (`carp.evaluation.scratch`).

    With `workers` > 1 the workers are spawned processes, which import the caller's main module again: a script that
    calls this at module level needs the usual `if __name__ == "__main__":` guard.
    """
    with scratch_directory() as scratch:
        onnx_directory = onnx_graphs_for(Path(checkpoint_path), backend, top_k, scratch)
        factory = functools.partial(
            PolicySource,
            checkpoint_path=Path(checkpoint_path),
            controller=controller,
            obs_steps=obs_steps,
            action_steps=action_steps,
            top_k=top_k,
            task_index=task_index,
            onnx_directory=onnx_directory,
        )
        results = evaluate_episodes(
            env_args,
            factory,
            seeds,
            obs_keys,
            obs_steps,
            max_steps,
            workers=workers,
            video_episodes=video_episodes,
            description="evaluate",
        )
    summary = summarize_episodes(
        successes=[r.success for r in results],
        steps=[r.steps for r in results],
        crashed=[bool(r.error) for r in results],
        prediction_seconds=[s for r in results for s in r.prediction_seconds],
        decoding_seconds=[s for r in results for s in r.decoding_seconds],
    )
    summary["top_k"] = top_k  # the report names each task's token choice
    return summary, results


def onnx_graphs_for(checkpoint_path: Path, backend: str, top_k: int, directory: Path) -> Path | None:
    """Export the checkpoint's graphs (token choice `top_k`) into `directory` when the ONNX Runtime backend applies.

    Returns:
        `directory` with the graphs, or None when the workers should run the PyTorch policy: `backend` is "torch",
        or the export failed (logged as a warning, evaluation goes on).
    """
    if backend not in EVAL_BACKENDS:
        raise ValueError(f"backend must be 'onnxruntime' or 'torch', got {backend!r}")
    if backend == "torch":
        return None
    try:
        return export_policy_graphs(CarpPolicy.load(checkpoint_path), directory, top_k)
    except Exception as error:  # an export problem must not cost the evaluation; PyTorch computes the same actions
        logger.warning(
            "ONNX export of %s failed (%s: %s); evaluating with PyTorch", checkpoint_path, type(error).__name__, error
        )
        return None


def episodes_table(results: Sequence[EpisodeResult]) -> pd.DataFrame:
    """Per-episode records: seed, success, steps, seconds, chunks, error."""
    rows = []
    for result in results:
        record = asdict(result)
        rows.append(
            {
                "seed": record["seed"],
                "success": record["success"],
                "steps": record["steps"],
                "seconds": round(record["seconds"], 3),
                "chunks": len(record["prediction_seconds"]),
                "error": record["error"],
            }
        )
    return pd.DataFrame(rows)


def batched_latency(policy, observations: np.ndarray, batch_size: int = 64, repeats: int = 20) -> dict[str, float]:
    """Per-chunk latency of the policy on a batch (keys ``batched_latency_*``), after two warm-up calls.

    Args:
        policy: a :class:`carp.policy.policy.CarpPolicy`.
        observations: (N, To, Do) raw observations; tiled or cut to ``batch_size``.
        batch_size: B.
        repeats: timed calls.
    """
    indices = np.arange(batch_size) % observations.shape[0]
    batch = torch.as_tensor(observations[indices], dtype=torch.float32)
    prediction, decoding = [], []
    for call in range(repeats + 2):
        timed = policy.predict_action_timed(batch)
        if call >= 2:
            prediction.append(timed.prediction_seconds)
            decoding.append(timed.decoding_seconds)
    return {
        "batched_latency_batch_size": batch_size,
        **latency_summary(prediction, "batched_latency_predict"),
        **latency_summary(decoding, "batched_latency_decode"),
    }


def save_gif(frames: Sequence[np.ndarray], path: Path, fps: int = 20, every: int = 2) -> Path:
    """Write RGB frames (H, W, 3) uint8 as an animated GIF (every ``every``-th frame), atomically."""
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(np.asarray(frame, dtype=np.uint8)) for frame in frames[::every]]
    temporary = path.with_name(f".{path.name}.tmp")
    images[0].save(
        temporary, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 * every / fps), loop=0
    )
    temporary.replace(path)
    return path
