"""Camera images for an image replay buffer: read from the robomimic file when it stores them, else rendered.

A robomimic image dataset stores ``obs/<camera>_image`` uint8 (T, H, W, 3) in every demo; those images are taken as
they are, so a user's robomimic image file ingests unchanged. A camera the file does not store is rendered from the
demos' stored simulator states (:mod:`carp.data.rendering`), so a low-dim file needs no new collection. Rendering
needs an offscreen OpenGL backend; the entry point chooses it (``MUJOCO_GL``) before MuJoCo is imported.
"""

import logging
import multiprocessing
from collections import deque
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from carp.data.render_cache import RenderCache
from carp.data.rendering import RenderingError, RenderSettings
from carp.data.robomimic_io import Demonstrations
from carp.data.robomimic_schema import (
    DatasetError,
    check_demo_layout,
    check_same_widths,
    hdf5_errors,
    open_hdf5,
    read_images,
)

STORED, RENDERED = "file", "rendered"

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ImagePlan:
    """Where each camera's images come from.

    Attributes:
        stored_keys: obs keys read from the file, in camera order.
        rendered: settings of the cameras rendered from states, or ``None`` when the file stores every camera.
    """

    stored_keys: tuple[str, ...]
    rendered: RenderSettings | None

    def sources(self, settings: RenderSettings) -> dict[str, str]:
        """Obs key -> ``file`` or ``rendered``, in camera order."""
        return {key: STORED if key in self.stored_keys else RENDERED for key in settings.image_keys}


def plan_images(path: Path, demo_names: Sequence[str], settings: RenderSettings) -> ImagePlan:
    """Decide per camera whether to read or render its images.

    A camera is read when any selected demo stores its key; the schema check then requires it in every demo, so a
    file that stores it in some demos only is refused rather than silently mixed with rendered frames.

    Args:
        path: the robomimic-schema file (already validated for its low-dim keys).
        demo_names: the demos that are ingested.
        settings: cameras, image size and render flags.
    """
    with open_hdf5(path) as handle, hdf5_errors(str(path)):
        present = set()
        for name in demo_names:
            obs = handle[f"data/{name}"].get("obs")
            present |= set(obs.keys()) if obs is not None else set()
    stored = tuple(key for key in settings.image_keys if key in present)
    missing = tuple(
        camera for camera, key in zip(settings.cameras, settings.image_keys, strict=True) if key not in stored
    )
    rendered = replace(settings, cameras=missing) if missing else None
    return ImagePlan(stored_keys=stored, rendered=rendered)


def check_stored_images(path: Path, names: Sequence[str], keys: Sequence[str], image_size: int) -> None:
    """Check the stored images of every demo from the file's metadata, before any of them is read.

    Raises:
        DatasetError: one line naming the file, demo, key and shape of an image dataset that is not uint8
            (T, image_size, image_size, 3) with T the demo's steps, or whose size differs between demos.
    """
    with open_hdf5(path) as handle, hdf5_errors(str(path)):
        layouts = [check_demo_layout(handle[f"data/{name}"], f"{path}: demo '{name}'", keys, None) for name in names]
    check_same_widths(path, names, layouts)
    for name, layout in zip(names, layouts, strict=True):
        for key in keys:
            if layout.obs_shapes[key] != (image_size, image_size, 3):
                shape = (layout.steps, *layout.obs_shapes[key])
                raise DatasetError(
                    f"{path}: demo '{name}': obs key '{key}': shape={shape}: expected "
                    f"(T, {image_size}, {image_size}, 3), the configured image size; images are not resized"
                )


def stored_episodes(path: Path, names: Sequence[str], keys: Sequence[str]) -> Iterator[dict[str, np.ndarray]]:
    """Read the stored images (checked by :func:`check_stored_images`) one demo at a time.

    Yields:
        Per demo, in the order of ``names``, obs key -> (T_i, H, W, 3) uint8 images as stored.
    """
    with open_hdf5(path) as handle:
        for name in names:
            where = f"{path}: demo '{name}'"
            with hdf5_errors(where):
                obs = handle[f"data/{name}/obs"]
            yield {key: read_images(obs[key], f"{where}: obs key '{key}'") for key in keys}


def check_renderable(demos: Demonstrations, settings: RenderSettings) -> None:
    """Refuse demos without stored states before anything is rendered.

    Raises:
        DatasetError: one line naming the file, demo and key.
    """
    for name, episode in zip(demos.names, demos.episodes, strict=True):
        states = episode.states
        if states is None or states.ndim != 2 or states.shape[1] == 0:
            shape = None if states is None else states.shape
            raise DatasetError(
                f"{demos.path}: demo '{name}': key 'states': shape={shape}: no simulator states to render "
                f"{list(settings.image_keys)} from (the file stores neither these images nor the states)"
            )


def rendered_episodes(
    demos: Demonstrations, settings: RenderSettings, cache: RenderCache | None = None, workers: int = 1
) -> Iterator[dict[str, np.ndarray]]:
    """Render the demos (checked by :func:`check_renderable`) one at a time, with a progress bar over frames.

    With a ``cache``, every demo rendered is saved there before it is yielded, and a demo the cache holds is read
    from it instead of rendered, so an ingestion interrupted after k demos renders only the others when run again.
    With ``workers`` > 1, that many spawned processes render demos ahead, each with its own simulator and OpenGL
    context; at most two demos per worker wait to be yielded, so memory stays a few demos whatever the file's size.

    Yields:
        Per demo, in file order, obs key -> (T_i, image_size, image_size, 3) uint8 upright RGB images.

    Raises:
        RenderingError: no offscreen backend, or a demo whose model is unknown (names the file and demo).
    """
    episodes = demos.episodes
    saved = {
        index
        for index, episode in enumerate(episodes)
        if cache is not None and cache.load(index, episode.length) is not None
    }
    if saved:
        logger.info("%s: %d demos rendered before are read from %s", demos.path, len(saved), cache.directory)
    missing = [index for index in range(len(episodes)) if index not in saved]
    fresh = _render_in_order(demos, settings, missing, workers)
    total = sum(episode.length for episode in episodes)
    try:
        with tqdm(total=total, desc=f"render {', '.join(settings.cameras)}", unit="frame") as progress:
            for index, episode in enumerate(episodes):
                images = cache.load(index, episode.length) if index in saved else None
                if images is None:
                    # An entry damaged since it was checked is rendered here, out of the workers' order.
                    source = fresh if index not in saved else _render_in_order(demos, settings, [index], 1)
                    rendered_index, images = next(source)
                    assert rendered_index == index
                    if cache is not None:
                        cache.save(index, images)
                progress.update(episode.length)
                yield images
    finally:
        fresh.close()


def _render_in_order(
    demos: Demonstrations, settings: RenderSettings, indices: Sequence[int], workers: int
) -> Iterator[tuple[int, dict[str, np.ndarray]]]:
    """Render the demos at ``indices``, yielding ``(index, images)`` in that order, here or on spawned workers."""
    from carp.data.rendering import render_states

    def named(index: int, error: RenderingError) -> RenderingError:
        return RenderingError(f"{demos.path}: demo '{demos.names[index]}': {error}")

    if not indices:
        return
    if workers <= 1 or len(indices) == 1:
        env = _make_env(demos.env_args)
        try:
            for index in indices:
                episode = demos.episodes[index]
                try:
                    images = render_states(env, episode.attrs, episode.states, settings)
                except RenderingError as error:
                    raise named(index, error) from None
                yield index, images
        finally:
            env.close()
        return
    # spawn: each worker builds its own MuJoCo model and OpenGL context; MUJOCO_GL is inherited from the environment.
    executor = ProcessPoolExecutor(
        max_workers=min(workers, len(indices)),
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_start_render_worker,
        initargs=(demos.env_args, settings),
    )
    queue = deque(indices)
    in_flight: deque = deque()
    try:
        while queue or in_flight:
            while queue and len(in_flight) < 2 * workers:
                index = queue.popleft()
                episode = demos.episodes[index]
                in_flight.append((index, executor.submit(_render_in_worker, episode.attrs, episode.states)))
            index, future = in_flight.popleft()
            try:
                images = future.result()
            except RenderingError as error:
                raise named(index, error) from None
            yield index, images
    finally:
        executor.shutdown(wait=True, cancel_futures=True)


def _make_env(env_args: Mapping):
    """The env a file's env_args describe, built by its task (which registers an env class carp defines)."""
    from carp.tasks import task_for_env_args

    return task_for_env_args(env_args).make_env(env_args)


def render_demos(
    env_args: Mapping,
    demos: Sequence[tuple[Mapping, np.ndarray]],
    settings: RenderSettings,
    description: str = "render",
) -> list[dict[str, np.ndarray]]:
    """Render the camera images of several demos of one file, with a progress bar over frames, in this process.

    Args:
        env_args: the file's ``data.attrs["env_args"]``.
        demos: per demo, its attributes and its (T_i, S) states.
        settings: cameras, size and render flags.
        description: label of the progress bar.

    Returns:
        Per demo, obs key -> (T_i, image_size, image_size, 3) uint8 images.
    """
    from carp.data.rendering import render_states

    env = _make_env(env_args)
    rendered = []
    try:
        with tqdm(total=sum(len(states) for _, states in demos), desc=description, unit="frame") as progress:
            for attrs, states in demos:
                rendered.append(render_states(env, attrs, states, settings))
                progress.update(len(states))
    finally:
        env.close()
    return rendered


_worker_state: dict = {}


def _start_render_worker(env_args: dict, settings: RenderSettings) -> None:
    _worker_state.update(env=_make_env(env_args), settings=settings)


def _render_in_worker(attrs: dict, states: np.ndarray) -> dict[str, np.ndarray]:
    from carp.data.rendering import render_states

    return render_states(_worker_state["env"], attrs, states, _worker_state["settings"])


__all__ = [
    "ImagePlan",
    "check_renderable",
    "check_stored_images",
    "plan_images",
    "render_demos",
    "rendered_episodes",
    "stored_episodes",
]
