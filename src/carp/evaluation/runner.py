"""Evaluate a policy checkpoint in simulation: parallel seeded episodes, summary metrics, batched latency, videos."""

import functools
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
import torch

from carp.config.checks import EVAL_BACKENDS
from carp.evaluation.metrics import latency_summary, measure_summary, summarize_episodes, task_score
from carp.evaluation.rollout import EpisodeResult, evaluate_episodes
from carp.evaluation.scratch import scratch_directory
from carp.evaluation.sources import PolicySource
from carp.policies.base import Deployment, Policy
from carp.policies.registry import load_policy
from carp.tasks import get_task
from carp.tasks.base import ActionFormat

if TYPE_CHECKING:
    from carp.data.dataset import TaskWindows
    from carp.data.rendering import RenderSettings

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class EvaluationSetup:
    """How a checkpoint's episodes run: the task's env and observation layout, the policy's settings and the workers.

    Attributes:
        env_args: the task's robomimic-style environment arguments (its replay buffer's ``env_args``).
        action_format: how the policy's actions become the env's (`carp.tasks.base.ActionFormat`).
        obs_keys: the low-dim observation keys, in the order the policy concatenates them.
        obs_steps: `To`.
        action_steps: `Ta`, actions of a chunk executed before the next prediction.
        max_steps: the episode's step limit.
        workers: episode processes (1: in this process).
        inference: the family's inference settings (`configure_inference`), e.g. CARP's ``{"top_k": 1}``; copied into
            the summary.
        backend: "onnxruntime" or "torch" (`Policy.deployment` decides what actually runs).
        cameras: what an image policy's steps render; None for state observations.
        task: the evaluated task: a policy trained on other tasks is refused, a multi-task policy runs with that
            task's statistics and id; None skips the check.
        task_index: the task id a multi-task policy is given when `task` does not select it; None otherwise.
        ensemble_m: None executes ``Ta`` actions per chunk; a number predicts at every step and executes the temporal
            ensemble of the overlapping chunks (`carp.evaluation.sources.ChunkEnsemble`).
    """

    env_args: dict
    action_format: ActionFormat
    obs_keys: Sequence[str]
    obs_steps: int
    action_steps: int
    max_steps: int
    workers: int = 1
    inference: Mapping[str, Any] = field(default_factory=dict)
    backend: str = "onnxruntime"
    cameras: "RenderSettings | None" = None
    task: str | None = None
    task_index: int | None = None
    ensemble_m: float | None = None


def evaluate_policy(
    checkpoint_path: Path, seeds: Sequence[int], setup: EvaluationSetup, video_episodes: int = 0
) -> tuple[dict[str, Any], list[EpisodeResult]]:
    """Run one episode per seed with the checkpoint's policy, of any family; returns the summary and the episodes.

    Each worker process loads the policy once and runs it on one CPU thread rather than sharing one policy batched
    across the workers' envs (`benchmarks/eval_batching.py` compares the two): a chunk's prediction costs far less
    than the simulator steps it drives, so batching would save little while adding a round trip between processes on
    every decision.

    The policy's family decides how `backend` is served (`Policy.deployment`): CARP exports ONNX graphs for
    "onnxruntime" into a temporary directory that every worker runs with ONNX Runtime; families without graphs, and
    "torch", run the PyTorch policy. The summary's `backend` names what actually ran. Sampling draws come from a
    generator seeded with the episode's seed either way. The directory does not outlive a killed evaluation
    (`carp.evaluation.scratch`).

    An image policy gets `setup.cameras`: every step renders them from the simulator state as ingest rendered the
    demos, and the summary adds the rendering time per step (`render_step_ms_*`), apart from the policy's latency. A
    multi-task policy evaluated on `setup.task` runs from a copy of the checkpoint with the task selected, in the
    temporary directory. The first `video_episodes` episodes are recorded.

    With `setup.workers` > 1 the workers are spawned processes, which import the caller's main module again: a script
    that calls this at module level needs the usual `if __name__ == "__main__":` guard.
    """
    if setup.backend not in EVAL_BACKENDS:
        raise ValueError(f"backend must be one of {EVAL_BACKENDS}, got {setup.backend!r}")
    inference, task, cameras = dict(setup.inference), setup.task, setup.cameras
    policy = load_policy(Path(checkpoint_path))
    policy.configure_inference(**inference)
    with scratch_directory() as scratch:
        if task is not None:
            policy.select_task(task)
            if policy.tasks is not None:
                checkpoint_path = Path(scratch) / "selected_task.pt"
                policy.save(checkpoint_path)
        deployment = deploy(policy, Path(checkpoint_path), setup.backend, scratch)
        factory = functools.partial(
            PolicySource,
            deployment.load,
            action_format=setup.action_format,
            obs_steps=setup.obs_steps,
            action_steps=setup.action_steps,
            inference=inference,
            task_index=setup.task_index,
            ensemble_m=setup.ensemble_m,
        )
        results = evaluate_episodes(
            setup.env_args,
            factory,
            seeds,
            setup.obs_keys,
            setup.obs_steps,
            setup.max_steps,
            workers=setup.workers,
            video_episodes=video_episodes,
            description="evaluate",
            cameras=cameras,
        )
    summary: dict[str, Any] = summarize_episodes(
        successes=[r.success for r in results],
        steps=[r.steps for r in results],
        crashed=[bool(r.error) for r in results],
        prediction_seconds=[s for r in results for s in r.prediction_seconds],
        decoding_seconds=[s for r in results for s in r.decoding_seconds],
    )
    if cameras is not None:
        summary.update(latency_summary([s for r in results for s in r.render_seconds], "render_step"))
        # The camera encoder's share of the prediction time, so the report can give the latency without it.
        summary.update(latency_summary([s for r in results for s in r.encoding_seconds], "latency_encode"))
    summary.update(measure_summary([r.task_measures for r in results]))
    summary.update(repair_summary(results))
    summary["score"] = task_score(summary, None if task is None else get_task(task).score_measure)
    summary.update(inference)  # the report names each row's inference settings (CARP: its token choice)
    summary.update(policy_facts(policy))
    summary["backend"] = deployment.backend
    # Control steps per chunk, for the report's inference budget: one when every step predicts a chunk.
    summary["action_steps"] = setup.action_steps if setup.ensemble_m is None else 1
    summary["ensemble_m"] = setup.ensemble_m
    return summary, results


def repair_summary(results: Sequence[EpisodeResult]) -> dict[str, float]:
    """`repaired_chunks` of `predicted_chunks` (the tokenizer repaired their tokens) and `repaired_chunk_rate`.

    Empty for a policy that reports no repairs (every family but the next-token one over a kind other than
    carp_msvq, whose sampled sequences can be malformed, e.g. FAST's).
    """
    repaired = [count for result in results for count in result.repaired_chunks]
    if not repaired:
        return {}
    return {
        "repaired_chunks": int(sum(repaired)),
        "predicted_chunks": len(repaired),
        "repaired_chunk_rate": float(sum(repaired)) / len(repaired),
    }


def deploy(policy: Policy, checkpoint_path: Path, backend: str, directory: Path) -> Deployment:
    """How workers obtain `policy` (saved at `checkpoint_path`) on `backend` (`Policy.deployment`), always loadable.

    A family that runs its checkpoint itself in PyTorch leaves the loading to the caller (its `load` is None), since
    reading any family's checkpoint needs the registry above the families: here it is `load_policy` on the file.
    """
    deployment = policy.deployment(Path(checkpoint_path), backend, Path(directory))
    if deployment.load is None:
        return Deployment(deployment.backend, functools.partial(load_policy, Path(checkpoint_path)))
    return deployment


def policy_facts(policy: Policy) -> dict[str, Any]:
    """What the report shows of a policy besides its results: family, configuration, model calls, parameters."""
    return {
        "policy_type": policy.policy_type,
        "inference": policy.description,
        "model_calls_per_chunk": policy.model_calls_per_chunk,
        "num_parameters": policy.num_parameters,
    }


def episodes_table(results: Sequence[EpisodeResult]) -> pd.DataFrame:
    """Per-episode records: seed, success, steps, seconds, chunks, median chunk latency (ms), error, task measures.

    ``chunk_ms_median`` is the episode's median of prediction plus decoding per chunk at batch 1 (NaN without a
    chunk); the report's latency ratios resample it over episodes. A task's own measures
    (the task's ``measure``, e.g. Square's ``insertion_offset_mm``) follow as one column each.
    """
    rows = []
    for result in results:
        record = asdict(result)
        chunk_seconds = np.add(record["prediction_seconds"], record["decoding_seconds"])
        rows.append(
            {
                "seed": record["seed"],
                "success": record["success"],
                "steps": record["steps"],
                "seconds": round(record["seconds"], 3),
                "chunks": len(record["prediction_seconds"]),
                "chunk_ms_median": round(float(np.median(chunk_seconds)) * 1000, 4) if chunk_seconds.size else np.nan,
                "error": record["error"],
                **record["task_measures"],
            }
        )
    return pd.DataFrame(rows)


def batched_latency(
    policy,
    observations: np.ndarray,
    batch_size: int = 64,
    repeats: int = 20,
    images: Callable[[np.ndarray], np.ndarray] | None = None,
) -> dict[str, float]:
    """Per-chunk latency of the policy on a batch (keys ``batched_latency_*``), after two warm-up calls.

    Args:
        policy: a policy of any family (`carp.policies.base.Policy`), run in PyTorch.
        observations: (N, To, Do) raw observations; tiled or cut to ``batch_size``.
        batch_size: B.
        repeats: timed calls.
        images: for an image policy, reads the camera images of windows (indices into `observations` -> (b, To,
            cameras, 3, h, w) uint8); the latency then includes the camera encoder.
    """
    indices = np.arange(batch_size) % observations.shape[0]
    batch = torch.as_tensor(observations[indices], dtype=torch.float32)
    seen = {} if images is None else {"images": images(indices)}
    prediction, decoding, encoding = [], [], []
    for call in range(repeats + 2):
        timed = policy.predict_action_timed(batch, **seen)
        if call >= 2:
            prediction.append(timed.prediction_seconds)
            decoding.append(timed.decoding_seconds)
            encoding.append(timed.encoding_seconds)
    summary = {
        "batched_latency_batch_size": batch_size,
        **latency_summary(prediction, "batched_latency_predict"),
        **latency_summary(decoding, "batched_latency_decode"),
    }
    if images is not None:
        summary.update(latency_summary(encoding, "batched_latency_encode"))
    return summary


def buffer_latency(
    policy: Policy,
    windows: "TaskWindows",
    processed_dir: Path,
    horizon: int,
    obs_steps: int,
    action_steps: int,
    with_images: bool = False,
    batch_size: int = 64,
) -> dict[str, float]:
    """`batched_latency` on a task's own windows: the held-out episodes, or the training ones when none are held out.

    Args:
        policy: a policy of any family, run in PyTorch.
        windows: the task's state windows (`carp.data.dataset.load_task_windows` with the same H, To, Ta).
        processed_dir: the task's ``data/processed/<task>/`` directory, whose buffer holds the images.
        horizon: ``H``, the window length the policy was trained on.
        obs_steps: ``To``, observation steps per window.
        action_steps: ``Ta``, executed actions per window.
        with_images: the policy sees cameras: its batch carries the windows' stored images.
        batch_size: B.
    """
    from carp.data.image_windows import ImageWindowReader
    from carp.data.ingest import BUFFER_DIRNAME

    split = "valid" if len(windows.valid_obs) else "train"
    observations = windows.valid_obs if split == "valid" else windows.train_obs
    images = None
    if with_images:
        reader = ImageWindowReader(Path(processed_dir) / BUFFER_DIRNAME, horizon, obs_steps, action_steps, split)
        images = reader.images
    return batched_latency(policy, observations, batch_size=batch_size, images=images)


VIDEO_SUFFIX = ".gif"


def episode_videos(directory: Path, name: str) -> list[Path]:
    """The GIFs `write_episode_videos` wrote under ``name`` (``<name>_seed<seed>.gif``), in seed order."""
    paths = Path(directory).glob(f"{name}_seed*{VIDEO_SUFFIX}")
    return sorted(paths, key=lambda path: int(path.stem.rsplit("_seed", 1)[1]))


def write_episode_videos(results: Sequence[EpisodeResult], directory: Path, name: str) -> list[Path]:
    """Write each recorded episode as ``<directory>/<name>_seed<seed>.gif`` and drop earlier ones of that name.

    An earlier evaluation's GIFs of the same name would otherwise sit beside the new ones, and a report that shows
    every GIF of a policy would show episodes of a policy that no longer exists.

    Returns:
        The GIFs written, in episode order.
    """
    recorded = [result for result in results if result.frames]
    keep = {Path(directory) / f"{name}_seed{result.seed}{VIDEO_SUFFIX}" for result in recorded}
    for stale in episode_videos(directory, name):
        if stale not in keep:
            stale.unlink()
    return [save_gif(result.frames, Path(directory) / f"{name}_seed{result.seed}{VIDEO_SUFFIX}") for result in recorded]


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
