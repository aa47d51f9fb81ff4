"""The formats a user's demonstrations may come in, each a small strategy chosen by what the path holds.

- ``lerobot``: a folder holding ``meta/info.json``, a LeRobotDataset (:mod:`carp.data.lerobot`);
- ``robomimic``: anything else, a robomimic-schema HDF5 file (:mod:`carp.data.robomimic_io`).

The collect stage imports either into ``data/raw/<task>.hdf5`` (robomimic schema), so ingestion and everything after
it read one format. A robomimic file is copied byte for byte; a LeRobotDataset is converted, its episodes named
``demo_<episode_index>``, its splits written as masks and its tasks as attributes. Either way the input is checked
completely before the destination is replaced, and a failed check leaves it as it was. A task may derive the obs keys
a LeRobotDataset lacks from its other features (:mod:`carp.data.lerobot.derived`, Push-T from
``lerobot/pusht_keypoints``); a robomimic file must hold them.
"""

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from carp.data.lerobot import is_lerobot_dataset
from carp.data.lerobot.derived import FeatureAdapter
from carp.data.robomimic_io import Demonstrations, import_demonstrations, select_demos, write_demonstrations
from carp.data.robomimic_schema import check_valid_mask


@dataclass(frozen=True)
class DemoFormat:
    """One format: how to recognise a path in it and how to import it.

    Attributes:
        name: the format's name, recorded by :mod:`carp.data.sources`.
        holds: whether a path is in this format.
        importer: ``(source, destination, obs_keys, action_dim, filter_key, staging_dir, env_name, env_args,
            cameras, image_size, adapter)`` -> the demos read; see :func:`import_demos`.
    """

    name: str
    holds: Callable[[Path], bool]
    importer: Callable[..., Demonstrations]


def _import_robomimic(
    source, destination, obs_keys, action_dim, filter_key, staging_dir, env_name, env_args, cameras, image_size, adapter
):
    # A robomimic file's cameras are its `<camera>_image` keys, which ingestion reads (or renders) itself.
    return import_demonstrations(
        source, destination, obs_keys, action_dim=action_dim, filter_key=filter_key, staging_dir=staging_dir,
        env_name=env_name,
    )  # fmt: skip


def _import_lerobot(
    source, destination, obs_keys, action_dim, filter_key, staging_dir, env_name, env_args, cameras, image_size, adapter
):
    from carp.data.lerobot.reader import read_lerobot_demonstrations

    # Every episode is converted (ingestion applies the filter), after checking that the filter selects some.
    demos = read_lerobot_demonstrations(
        source,
        obs_keys,
        action_dim=action_dim,
        env_name=env_name,
        env_args=env_args() if env_args else None,
        cameras=cameras,
        image_size=image_size,
        adapter=adapter,
    )
    check_valid_mask(source, select_demos(source, demos.names, demos.masks, filter_key), demos.masks, filter_key)
    write_demonstrations(
        destination,
        demos.episodes,
        demos.env_args,
        file_attrs=demos.attrs,
        staging_dir=staging_dir,
        names=demos.names,
        masks=demos.masks,
    )
    return demos


LEROBOT = DemoFormat("lerobot", is_lerobot_dataset, _import_lerobot)
ROBOMIMIC = DemoFormat("robomimic", lambda path: True, _import_robomimic)
# Tried in order; robomimic, the fallback, takes every other path and reports what is wrong with it.
FORMATS = (LEROBOT, ROBOMIMIC)


def demo_format(path: Path) -> DemoFormat:
    """The format of ``path``: the first of :data:`FORMATS` that holds it."""
    return next(format_ for format_ in FORMATS if format_.holds(Path(path)))


def import_demos(
    source: Path,
    destination: Path,
    obs_keys: Sequence[str],
    action_dim: int | None = None,
    filter_key: str | None = None,
    staging_dir: Path | None = None,
    env_name: str | None = None,
    env_args: Callable[[], dict] | None = None,
    cameras: Sequence[str] = (),
    image_size: int = 84,
    adapter: FeatureAdapter | None = None,
) -> Demonstrations:
    """Check a user's demos in any format of :data:`FORMATS` and write them to ``destination`` as a robomimic file.

    Args:
        source: a robomimic-schema HDF5 file or a LeRobotDataset folder; every message names it.
        destination: the ``.hdf5`` to write, replaced only once ``source`` passed every check.
        obs_keys: low-dim observation keys every demo must have.
        action_dim: expected action width; ``None`` accepts any.
        filter_key: the mask (robomimic) or split (LeRobot) ingestion will select; it must exist.
        staging_dir: where the output is built before its rename (see :mod:`carp.data.staging`).
        env_name: the ``env_name`` the demos' env_args must name; ``None`` accepts any.
        env_args: gives the env_args of a source that records none (a LeRobotDataset not exported by carp);
            called only then.
        cameras: cameras a LeRobotDataset's videos are decoded for, stored as ``obs/<camera>_image`` uint8
            (T, image_size, image_size, 3) (:mod:`carp.data.lerobot.videos`).
        image_size: side of those images in pixels.
        adapter: the task's derivation of obs keys a LeRobotDataset lacks from its other features
            (:mod:`carp.data.lerobot.derived`); not read for a robomimic file.

    Raises:
        DatasetError: ``source`` is unusable; ``destination`` is left as it was.
        OSError: the copy or write failed; ``destination`` is left as it was.
    """
    format_ = demo_format(source)
    return format_.importer(
        Path(source),
        Path(destination),
        obs_keys,
        action_dim,
        filter_key,
        staging_dir,
        env_name,
        env_args,
        tuple(cameras),
        image_size,
        adapter,
    )
