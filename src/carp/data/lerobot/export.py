"""``carp export-lerobot``: a robomimic-schema file of a registered task -> a LeRobotDataset v3.0 folder.

The file's task (its ``env_args``, `carp.tasks.task_for_env_args`) gives the frame rate (its control frequency), the
keys of ``observation.state`` (its default observation keys) and the task text; every low-dim obs key of the file is
exported on its own as well, and the camera images it stores (obs keys ending in ``_image``) as MP4 videos
(:mod:`carp.data.lerobot.writer`). A file without images (carp's scripted demos render theirs at ingestion) exports
no camera.
"""

from dataclasses import dataclass
from pathlib import Path

from carp.data.lerobot.writer import write_lerobot_dataset
from carp.data.robomimic_io import DatasetError, read_demonstrations, read_env_args, read_obs_keys
from carp.data.robomimic_schema import IMAGE_KEY_SUFFIX, is_image_key
from carp.tasks import task_for_env_args


@dataclass(frozen=True)
class ExportSummary:
    """What an export wrote: episodes, frames, the fps, the low-dim obs keys and the cameras."""

    episodes: int
    frames: int
    fps: int
    obs_keys: tuple[str, ...]
    cameras: tuple[str, ...]


def export_lerobot(source: Path, output: Path, staging_dir: Path | None = None) -> ExportSummary:
    """Read and check ``source`` as ingestion does, then write it as a LeRobotDataset at ``output`` atomically.

    Raises:
        DatasetError: ``source`` is unusable or names no registered task; ``output`` is left as it was.
    """
    source = Path(source)
    env_args = read_env_args(source)
    try:
        task = task_for_env_args(env_args)
    except ValueError as error:
        raise DatasetError(f"{source}: {error}") from None
    keys = read_obs_keys(source)
    low_dim = tuple(key for key in keys if not is_image_key(key))
    images = tuple(key for key in keys if is_image_key(key))
    demos = read_demonstrations(source, (*low_dim, *images))
    state_keys = [key for key in task.default_obs_keys if key in low_dim]
    write_lerobot_dataset(
        demos,
        output,
        fps=task.control_frequency_hz,
        state_keys=state_keys,
        task_text=task.name,
        staging_dir=staging_dir,
    )
    return ExportSummary(
        episodes=len(demos.episodes),
        frames=sum(episode.length for episode in demos.episodes),
        fps=task.control_frequency_hz,
        obs_keys=low_dim,
        cameras=tuple(key.removesuffix(IMAGE_KEY_SUFFIX) for key in images),
    )
