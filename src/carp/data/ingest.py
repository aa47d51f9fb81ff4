"""Ingestion: a robomimic-schema HDF5 file -> replay buffer + normalization statistics.

The file's task (named by its ``env_args``, `carp.tasks.task_for_env_args`) and the controller decide how actions are
stored (the task's `ActionFormat`): absolute 7-D arm actions (pos, axis-angle, gripper) become 10-D (pos, 6-D
rotation, gripper) and are converted back exactly when executed; delta arm actions and Push-T's 2-D targets are kept
as they are. The output directory is built under a temporary name and renamed at the end, so a failed or interrupted
ingestion never leaves a partial directory at the output path. Every check of the input file lives in
:mod:`carp.data.robomimic_schema`, shared with the collect stage's import of a user's file.

With camera settings, the buffer also holds each camera's images (read from the file or rendered from the stored
states, see :mod:`carp.data.camera_images`), written into the staged store one demo at a time; without them the
output is exactly the low-dim buffer.
"""

import json
import os
import shutil
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from carp.data.camera_images import (
    ImagePlan,
    check_renderable,
    check_stored_images,
    plan_images,
    rendered_episodes,
    stored_episodes,
)
from carp.data.normalizer import MinMaxNormalizer, save_normalizers
from carp.data.render_cache import RenderCache, render_key
from carp.data.rendering import RenderSettings
from carp.data.replay_buffer import ReplayBuffer
from carp.data.robomimic_io import DatasetError, Demonstrations, check_env_name, read_demonstrations, read_env_args
from carp.data.robomimic_schema import check_valid_mask, is_image_key
from carp.data.staging import staged
from carp.data.subsets import nested_subset
from carp.tasks import task_for_env_args
from carp.tasks.base import ActionFormat

BUFFER_DIRNAME = "replay.zarr"
NORMALIZATION_FILENAME = "normalization.json"
SUMMARY_FILENAME = "summary.json"


@dataclass(frozen=True)
class IngestSummary:
    """What an ingestion produced."""

    source: str
    episodes: int
    valid_episodes: int
    steps: int
    obs_dim: int
    action_dim: int
    mean_episode_steps: float


def ingest_demonstrations(
    raw_path: Path,
    output_dir: Path,
    obs_keys: Sequence[str],
    controller: str = "absolute",
    filter_key: str | None = None,
    valid_fraction: float = 0.1,
    staging_dir: Path | None = None,
    camera_settings: RenderSettings | None = None,
    render_workers: int = 1,
    subset_size: int = 0,
    subset_seed: int = 0,
    env_name: str | None = None,
    source_name: str | None = None,
) -> IngestSummary:
    """Convert a robomimic-schema file into ``output_dir/{replay.zarr, normalization.json, summary.json}``.

    Args:
        raw_path: robomimic-schema HDF5 of a registered task (its ``env_args``), actions as the env takes them.
        output_dir: replaced atomically on success; untouched on failure.
        obs_keys: low-dim obs keys, concatenated in this order into ``obs`` (N, Do).
        controller: with the file's task, the action format (arm tasks: ``absolute`` converts actions to 10-D,
            ``delta`` keeps 7-D).
        filter_key: optional ``mask/<filter_key>`` restricting the demos.
        valid_fraction: share of episodes held out when the file has no ``mask/valid`` (a ``mask/valid`` listing
            every demo is refused; with ``filter_key`` ``valid``, the mask is the selection and this share is held
            out of it).
        staging_dir: where the output is built before its rename (see :mod:`carp.data.staging`): outside every
            folder a pipeline declares as a dependency, on the output's filesystem. ``None`` uses ``output_dir``'s
            parent.
        camera_settings: cameras and image size of an image buffer; ``None`` (the default) stores low-dim
            observations only.
        render_workers: processes rendering the cameras the file does not store (see
            :func:`carp.data.camera_images.rendered_episodes`).
        subset_size: keep this many of the file's demos (`carp.data.subsets.nested_subset`); 0 keeps every demo.
        subset_seed: seed of the subset's shuffle.
        env_name: the env the file must come from (the pipeline task's ``env_name``); ``None`` accepts any task's.
        source_name: what the buffer and the summary record as the demos' source; ``None`` records ``raw_path`` as
            given. A pipeline names the file relative to its project, so that the output's bytes, and with them the
            hashes of every later stage, do not depend on the folder the project lives in.

    Raises:
        DatasetError: one line naming the file, demo and key of the first problem found.
        RenderingError: images must be rendered and rendering is unavailable, or a demo's model is unknown.
    """
    raw_path, output_dir = Path(raw_path), Path(output_dir)
    source = str(raw_path) if source_name is None else source_name
    action_format = _action_format(raw_path, controller, env_name)
    demos = read_demonstrations(raw_path, obs_keys, action_dim=action_format.stored_dim, filter_key=filter_key)
    if subset_size:
        if subset_size > len(demos.names):
            raise DatasetError(f"{raw_path}: holds {len(demos.names)} demos, fewer than a subset of {subset_size}")
        kept = set(nested_subset(demos.names, subset_size, subset_seed))
        demos = replace(
            demos,
            names=[name for name in demos.names if name in kept],
            episodes=[episode for name, episode in zip(demos.names, demos.episodes) if name in kept],
        )
        check_valid_mask(raw_path, demos.names, demos.masks, filter_key)
    images = [key for key in obs_keys if is_image_key(key)]
    if images:
        # Checked after reading, so that a damaged file is reported as such first.
        raise DatasetError(
            f"{raw_path}: obs keys {images}: camera images are not stored in the low-dimensional replay buffer; "
            "list only low-dimensional obs keys"
        )
    plan = _plan_images(demos, camera_settings) if camera_settings is not None else None
    valid_names = _valid_demo_names(demos.names, demos.masks.get("valid", []), valid_fraction)

    obs_parts, action_parts, ends = [], [], []
    total = 0
    for episode in demos.episodes:
        obs_parts.append(np.concatenate([episode.obs[key] for key in obs_keys], axis=1))
        action_parts.append(action_format.to_policy(episode.actions))
        total += episode.length
        ends.append(total)
    # Statistics are fitted on the float32 values the buffer stores, so normalized data lies exactly in [-1, 1].
    obs = np.concatenate(obs_parts).astype(np.float32)
    action = np.concatenate(action_parts).astype(np.float32)
    first = demos.episodes[0]
    buffer = ReplayBuffer(
        obs=obs,
        action=action,
        episode_ends=np.asarray(ends, dtype=np.int64),
        valid_episodes=np.asarray([name in valid_names for name in demos.names]),
        attrs={
            "obs_keys": list(obs_keys),
            "obs_widths": [int(first.obs[key].shape[1]) for key in obs_keys],
            "controller": controller,
            "source": source,
            "env_args": demos.env_args,
            "demo_names": demos.names,
        },
    )
    summary = IngestSummary(
        source=source,
        episodes=buffer.num_episodes,
        valid_episodes=int(buffer.valid_episodes.sum()),
        steps=int(total),
        obs_dim=int(obs.shape[1]),
        action_dim=int(action.shape[1]),
        mean_episode_steps=float(total / buffer.num_episodes),
    )

    if camera_settings is not None:
        buffer.attrs.update(
            image_keys=list(camera_settings.image_keys),
            image_size=camera_settings.image_size,
            image_sources=plan.sources(camera_settings),
        )

    normalizers = {"obs": MinMaxNormalizer.fit(obs), "action": MinMaxNormalizer.fit(action)}
    output_dir.parent.mkdir(parents=True, exist_ok=True)
    staging_dir = Path(staging_dir or output_dir.parent)
    cache = None
    if plan is not None and plan.rendered is not None:
        key = render_key(demos.env_args, [(e.attrs, e.states) for e in demos.episodes], plan.rendered)
        cache = RenderCache(staging_dir / f".{output_dir.name}.render-cache", key, plan.rendered)
    with staged(staging_dir, output_dir.name) as staging:
        staging.mkdir()
        buffer.save(staging / BUFFER_DIRNAME)
        if camera_settings is not None:
            _write_images(staging / BUFFER_DIRNAME, buffer, demos, camera_settings, plan, cache, render_workers)
        save_normalizers(staging / NORMALIZATION_FILENAME, normalizers)
        (staging / SUMMARY_FILENAME).write_text(json.dumps(asdict(summary), indent=2))
        if output_dir.exists():
            shutil.rmtree(output_dir)
        os.replace(staging, output_dir)
    if cache is not None:
        cache.remove()
    return summary


def _action_format(raw_path: Path, controller: str, env_name: str | None) -> ActionFormat:
    """The action format of the file's task under ``controller``; DatasetError naming the file when there is none."""
    env_args = read_env_args(raw_path)
    check_env_name(raw_path, env_args, env_name)
    try:
        task = task_for_env_args(env_args)
        return task.action_format(controller)
    except ValueError as error:
        raise DatasetError(f"{raw_path}: {error}") from None


def _plan_images(demos: Demonstrations, settings: RenderSettings) -> ImagePlan:
    """Choose each camera's source and check it from metadata, before any output is staged."""
    plan = plan_images(demos.path, demos.names, settings)
    if plan.stored_keys:
        check_stored_images(demos.path, demos.names, plan.stored_keys, settings.image_size)
    if plan.rendered is not None:
        check_renderable(demos, plan.rendered)
    return plan


def _write_images(
    root: Path,
    buffer: ReplayBuffer,
    demos: Demonstrations,
    settings: RenderSettings,
    plan: ImagePlan,
    cache: RenderCache | None,
    render_workers: int,
) -> None:
    """Fill ``data/<camera>_image`` of the saved store ``root`` one demo at a time, so no camera is ever held whole.

    Rendered demos go through ``cache``, which keeps them until the ingestion is complete.
    """
    steps = int(buffer.episode_ends[-1])
    arrays = {
        key: ReplayBuffer.create_image_array(root, key, steps, settings.image_size) for key in settings.image_keys
    }
    sources = []
    if plan.stored_keys:
        sources.append(stored_episodes(demos.path, demos.names, plan.stored_keys))
    if plan.rendered is not None:
        sources.append(rendered_episodes(demos, plan.rendered, cache, render_workers))
    starts, ends = buffer.episode_starts, buffer.episode_ends
    for episodes in sources:
        for index, images in enumerate(episodes):
            for key, frames in images.items():
                arrays[key][starts[index] : ends[index]] = frames


def _valid_demo_names(names: list[str], listed_valid: list[str], valid_fraction: float) -> set[str]:
    """Held-out demos: the file's ``mask/valid`` when it selects a proper subset, else the last ``valid_fraction``."""
    selected = set(listed_valid) & set(names)
    if selected and len(selected) < len(names):
        return selected
    if len(names) < 2 or valid_fraction <= 0:
        return set()
    count = max(1, int(round(valid_fraction * len(names))))
    return set(names[-count:])


__all__ = ["DatasetError", "IngestSummary", "ingest_demonstrations"]
