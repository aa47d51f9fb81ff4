"""Read a LeRobotDataset folder (layouts in :mod:`carp.data.lerobot`) as carp :class:`Demonstrations`.

Episodes are split by ``episode_index`` and kept in that order; demo ``demo_<episode_index>`` holds the frames of one
episode. Checks, each failure one :class:`DatasetError` line naming the file, the episode and the key, all done before
the caller writes anything:

1. ``meta/`` (:func:`carp.data.lerobot.metadata.read_metadata`): version, fps, features, episode index, tasks, totals;
2. the features carp reads exist in ``info.json`` with a numeric dtype and a 1-D shape (the action width the task
   expects), and every data file has their columns with that dtype and width in every row, without nulls;
3. every data file holds the frames of the episodes the index places in it and no others, each episode's frame count
   equals its listed length, its ``frame_index`` runs 0, 1, ..., T-1 and consecutive timestamps differ by 1 / fps
   (within LeRobot's own tolerance), and its ``task_index`` values are in the task table;
4. values are finite in float32 with column ranges that normalization can divide by (the robomimic checks,
   :mod:`carp.data.robomimic_schema`);
5. with cameras, each is a video feature of (H, W, 3) frames with a frame at every step's time
   (:mod:`carp.data.lerobot.videos`).

A task may derive obs keys the dataset lacks from other features (:mod:`carp.data.lerobot.derived`): given its
adapter, the reader checks and reads the adapter's source features instead, and the adapter's checks name the file,
the episode and the frame like the reader's own.
"""

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from carp.data.lerobot.derived import FeatureAdapter
from carp.data.lerobot.metadata import (
    CAMERA_DTYPES,
    INFO_PATH,
    NUMERIC_DTYPES,
    EpisodeEntry,
    Feature,
    Metadata,
    read_metadata,
    read_parquet_table,
)
from carp.data.lerobot.videos import camera_feature_names, decode_episode, image_key
from carp.data.robomimic_io import Demonstrations, Episode, check_env_name, select_demos
from carp.data.robomimic_schema import DatasetError, check_stored_dtype, check_stored_ranges, check_valid_mask

ACTION = "action"
REWARD = "next.reward"
DONE = "next.done"
SIM_STATE = "sim_state"
# Keys of an adapter's source features among the columns read, apart from the obs keys.
SOURCE_PREFIX = "source:"
OBSERVATION_PREFIX = "observation."
# LeRobot's default tolerance when it checks that timestamps advance by 1 / fps (its ``tolerance_s``).
TIMESTAMP_TOLERANCE_S = 1e-4


def demo_name(episode_index: int) -> str:
    """The carp demo name of a LeRobot episode."""
    return f"demo_{episode_index}"


def obs_feature_name(key: str, features: dict[str, Feature]) -> str | None:
    """The feature an obs key names: ``key`` itself, else ``observation.<key>``; None when neither exists."""
    for name in (key, OBSERVATION_PREFIX + key):
        if name in features:
            return name
    return None


def read_lerobot_demonstrations(
    root: Path,
    obs_keys: Sequence[str],
    action_dim: int | None = None,
    filter_key: str | None = None,
    env_name: str | None = None,
    env_args: dict | None = None,
    cameras: Sequence[str] = (),
    image_size: int = 84,
    adapter: FeatureAdapter | None = None,
) -> Demonstrations:
    """Read and check the episodes of a LeRobotDataset folder.

    Args:
        root: the dataset folder (holds ``meta/info.json``).
        obs_keys: low-dim observation keys; each names the feature ``key`` or ``observation.<key>``, (T, D_key).
        action_dim: expected width A of ``action``; ``None`` accepts any.
        filter_key: a split of ``info.json``'s ``splits`` selecting the episodes; ``None`` reads all.
        env_name: the ``env_name`` the env_args must name; ``None`` accepts any.
        env_args: the env_args of a dataset without carp's ``meta/carp.json`` (the task's own); ``None`` requires
            that file.
        cameras: cameras whose video features are decoded into ``obs["<camera>_image"]``, (T, S, S, 3) uint8.
        image_size: S, the side of the camera images.
        adapter: the task's derivation of its obs keys from other features, used when one of the keys it provides
            names no feature; ``None`` requires every obs key as a feature.

    Returns:
        Demonstrations whose episodes hold ``obs[key]`` (T, D_key) float64, ``actions`` (T, A) float64, ``rewards``
        and ``dones`` (T,) and ``states`` (T, S) when the dataset (or the adapter) has them, and ``attrs`` with the
        episode index and its task texts; the splits become ``masks``.

    Raises:
        DatasetError: one line naming the file, the episode and the key of the first problem.
    """
    root = Path(root)
    meta = read_metadata(root)
    env_args = _env_args(meta, env_args)
    check_env_name(root, env_args, env_name)
    adapter = _adapter_in_use(meta, obs_keys, adapter)
    read_keys = [key for key in obs_keys if adapter is None or key not in adapter.provides]
    columns = _columns(meta, read_keys, action_dim)
    if adapter is not None:
        columns.update(_adapter_columns(meta, adapter))
    videos = {camera: _video_feature(meta, camera) for camera in cameras}
    all_names = [demo_name(entry.index) for entry in meta.episodes]
    masks = {name: [demo_name(index) for index in indices] for name, indices in meta.splits.items()}
    names = select_demos(root, all_names, masks, filter_key)
    check_valid_mask(root, names, masks, filter_key)
    wanted = set(names)
    entries = [entry for entry in meta.episodes if demo_name(entry.index) in wanted]
    episodes = _read_episodes(meta, entries, columns, videos, image_size, adapter)
    check_stored_ranges(root, names, f"key '{ACTION}'", [episode.actions for episode in episodes])
    for key in obs_keys:
        check_stored_ranges(root, names, f"obs key '{key}'", [episode.obs[key] for episode in episodes])
    attrs = {
        **_carp_object(meta, "attrs"),
        "lerobot_codebase_version": meta.version,
        "lerobot_fps": meta.fps,
        "lerobot_tasks": [meta.tasks[index] for index in sorted(meta.tasks)],
    }
    return Demonstrations(path=root, env_args=env_args, names=names, episodes=episodes, attrs=attrs, masks=masks)


def _carp_object(meta: Metadata, key: str) -> dict:
    """An object-valued entry of ``meta/carp.json`` (``{}`` when absent)."""
    value = meta.carp.get(key, {})
    if not isinstance(value, dict):
        raise DatasetError(f"{meta.root / 'meta/carp.json'}: key '{key}'={value!r}: expected an object")
    return value


def _env_args(meta: Metadata, fallback: dict | None) -> dict:
    where = meta.root / "meta/carp.json"
    if "env_args" in meta.carp:
        if not isinstance(meta.carp["env_args"], dict):
            raise DatasetError(f"{where}: key 'env_args'={meta.carp['env_args']!r}: expected an object")
        return meta.carp["env_args"]
    if fallback is None:
        raise DatasetError(f"{where}: key 'env_args': missing, and no task names the environment")
    return dict(fallback)


def _adapter_in_use(meta: Metadata, obs_keys: Sequence[str], adapter: FeatureAdapter | None) -> FeatureAdapter | None:
    """``adapter`` when one of the obs keys it provides names no feature, else None (the keys are read as stored)."""
    if adapter is None:
        return None
    missing = [key for key in obs_keys if key in adapter.provides and obs_feature_name(key, meta.features) is None]
    return adapter if missing else None


def _adapter_columns(meta: Metadata, adapter: FeatureAdapter) -> dict[str, Feature]:
    """The adapter's source features (keyed :data:`SOURCE_PREFIX` + name), checked against ``info.json``."""
    info = meta.root / INFO_PATH
    missing = [key for key in adapter.provides if obs_feature_name(key, meta.features) is None]
    columns = {}
    for name, width in adapter.sources.items():
        feature = meta.features.get(name)
        if feature is None or _low_dim(info, feature).shape != (width,):
            found = "no such feature" if feature is None else f"shape={list(feature.shape)}"
            raise DatasetError(
                f"{info}: obs keys {missing}: not features of this dataset, and feature '{name}': {found}, so they "
                f"cannot be derived either; the layout that works: {adapter.layout} (features: {sorted(meta.features)})"
            )
        columns[SOURCE_PREFIX + name] = feature
    return columns


def _columns(meta: Metadata, obs_keys: Sequence[str], action_dim: int | None) -> dict[str, Feature]:
    """Obs key, ``action`` and the optional keys -> the feature each reads, checked against ``info.json``."""
    info = meta.root / INFO_PATH
    columns = {}
    for key in obs_keys:
        name = obs_feature_name(key, meta.features)
        if name is None:
            raise DatasetError(
                f"{info}: obs key '{key}': no feature '{key}' or '{OBSERVATION_PREFIX}{key}' "
                f"(features: {sorted(meta.features)})"
            )
        columns[key] = _low_dim(info, meta.features[name])
    if ACTION not in meta.features:
        raise DatasetError(f"{info}: key '{ACTION}': no such feature (features: {sorted(meta.features)})")
    action = _low_dim(info, meta.features[ACTION])
    if action_dim is not None and action.shape != (action_dim,):
        raise DatasetError(
            f"{info}: feature '{ACTION}': shape={list(action.shape)}: expected [{action_dim}], this task's action width"
        )
    columns[ACTION] = action
    for name in (REWARD, DONE, SIM_STATE):
        if name in meta.features:
            columns[name] = _low_dim(info, meta.features[name])
    return columns


def _video_feature(meta: Metadata, camera: str) -> Feature:
    info = meta.root / INFO_PATH
    names = camera_feature_names(camera)
    name = next((name for name in names if name in meta.features), None)
    if name is None:
        raise DatasetError(
            f"{info}: camera '{camera}': no feature {' or '.join(repr(n) for n in names)} (features: "
            f"{sorted(meta.features)})"
        )
    feature = meta.features[name]
    if feature.dtype != "video":
        raise DatasetError(f"{info}: feature '{name}': dtype={feature.dtype!r}: cameras are read from video features")
    if len(feature.shape) != 3 or feature.shape[-1] != 3:
        raise DatasetError(f"{info}: feature '{name}': shape={list(feature.shape)}: expected [H, W, 3] RGB frames")
    return feature


def _low_dim(info: Path, feature: Feature) -> Feature:
    where = f"{info}: feature '{feature.name}'"
    if feature.dtype in CAMERA_DTYPES:
        raise DatasetError(f"{where}: dtype={feature.dtype!r}: camera features are not read (low-dim features only)")
    if feature.dtype not in NUMERIC_DTYPES:
        raise DatasetError(f"{where}: dtype={feature.dtype!r}: expected numbers, one of {list(NUMERIC_DTYPES)}")
    if len(feature.shape) != 1:
        raise DatasetError(f"{where}: shape={list(feature.shape)}: expected one dimension, [D]")
    return feature


def _read_episodes(
    meta: Metadata,
    entries: list[EpisodeEntry],
    columns: dict[str, Feature],
    videos: dict[str, Feature],
    image_size: int,
    adapter: FeatureAdapter | None,
) -> list[Episode]:
    """The episodes of ``entries``, reading each data file once."""
    by_file: dict[Path, list[EpisodeEntry]] = {}
    for entry in meta.episodes:
        by_file.setdefault(entry.data_file, []).append(entry)
    wanted = {entry.index for entry in entries}
    episodes = {}
    for data_file, placed in by_file.items():
        if not wanted & {entry.index for entry in placed}:
            continue
        frames = _FileFrames(meta, meta.root / data_file, columns, videos, image_size, adapter)
        frames.check_episodes(placed)
        for entry in placed:
            if entry.index in wanted:
                episodes[entry.index] = frames.episode(entry)
    return [episodes[entry.index] for entry in entries]


class _FileFrames:
    """The frames of one data file, with every check that names the file, an episode and a key."""

    def __init__(
        self,
        meta: Metadata,
        path: Path,
        columns: dict[str, Feature],
        videos: dict[str, Feature],
        image_size: int,
        adapter: FeatureAdapter | None,
    ):
        self.meta, self.path, self.columns = meta, path, columns
        self.videos, self.image_size, self.adapter = videos, image_size, adapter
        if not path.is_file():
            raise DatasetError(f"{path}: file not found (the episode index places episodes in it)")
        try:
            schema = pq.read_schema(path)
        except (OSError, pa.ArrowException) as error:
            raise DatasetError(f"{path}: cannot be read as Parquet ({str(error).strip()[:200]})") from None
        needed = ["episode_index", "frame_index", "timestamp", "task_index", *{f.name for f in columns.values()}]
        for name in needed:
            if name not in schema.names:
                raise DatasetError(f"{path}: key '{name}': column missing (columns: {schema.names})")
        self.table = read_parquet_table(path, columns=list(dict.fromkeys(needed)))
        self.episode_ids = None
        self.converted: dict[str, np.ndarray] = {}
        self.episode_ids = self._integers("episode_index")

    def _locate(self, row: int) -> str:
        if self.episode_ids is None:
            return f"row {row}"
        episode = int(self.episode_ids[row])
        first = int(np.flatnonzero(self.episode_ids == episode)[0])
        return f"episode {episode}: step {row - first}"

    def _column(self, name: str) -> pa.Array:
        column = self.table.column(name).combine_chunks()
        if column.null_count:
            row = int(np.flatnonzero(column.is_null().to_numpy(zero_copy_only=False))[0])
            raise DatasetError(f"{self.path}: {self._locate(row)}: key '{name}': value missing (null)")
        return column

    def _integers(self, name: str) -> np.ndarray:
        # Each column is converted once per file, not once per episode: a v3.0 file holds many episodes.
        if name in self.converted:
            return self.converted[name]
        column = self._column(name)
        if not pa.types.is_integer(column.type):
            raise DatasetError(f"{self.path}: key '{name}': type={column.type}: expected integers")
        self.converted[name] = column.to_numpy(zero_copy_only=False).astype(np.int64)
        return self.converted[name]

    def values(self, feature: Feature) -> np.ndarray:
        """The column of a 1-D feature as (N, D) float64, checked against its dtype and width in every row."""
        if feature.name not in self.converted:
            self.converted[feature.name] = self._values(feature)
        return self.converted[feature.name]

    def _values(self, feature: Feature) -> np.ndarray:
        column, width, name = self._column(feature.name), feature.shape[0], feature.name
        kind = column.type
        if pa.types.is_list(kind) or pa.types.is_large_list(kind) or pa.types.is_fixed_size_list(kind):
            lengths = pc.list_value_length(column).to_numpy(zero_copy_only=False)
            wrong = np.flatnonzero(lengths != width)
            if wrong.size:
                row = int(wrong[0])
                raise DatasetError(
                    f"{self.path}: {self._locate(row)}: key '{name}': holds {int(lengths[row])} values, "
                    f"info.json's shape is [{width}]"
                )
            items = column.flatten()
            if items.null_count:
                row = int(np.flatnonzero(items.is_null().to_numpy(zero_copy_only=False))[0]) // width
                raise DatasetError(f"{self.path}: {self._locate(row)}: key '{name}': value missing (null)")
            value_type = kind.value_type
            flat = items.to_numpy(zero_copy_only=False)
        elif width == 1 and (pa.types.is_integer(kind) or pa.types.is_floating(kind) or pa.types.is_boolean(kind)):
            value_type, flat = kind, column.to_numpy(zero_copy_only=False)
        else:
            raise DatasetError(f"{self.path}: key '{name}': type={kind}: expected [{width}] numbers per frame")
        if _dtype_name(value_type) != feature.dtype:
            raise DatasetError(
                f"{self.path}: key '{name}': dtype={_dtype_name(value_type)}: info.json declares {feature.dtype}"
            )
        return np.asarray(flat, dtype=np.float64).reshape(-1, width)

    def check_episodes(self, placed: list[EpisodeEntry]) -> None:
        """The file holds exactly the frames of the episodes the index places in it, in their listed lengths."""
        listed = {entry.index for entry in placed}
        stray = sorted(set(np.unique(self.episode_ids).tolist()) - listed)
        if stray:
            raise DatasetError(
                f"{self.path}: episode {stray[0]}: key 'episode_index': frames of an episode the index does not "
                f"place in this file (it lists {sorted(listed)})"
            )
        for entry in placed:
            rows = np.flatnonzero(self.episode_ids == entry.index)
            if rows.size != entry.length:
                raise DatasetError(
                    f"{self.path}: episode {entry.index}: key 'episode_index': {rows.size} frames, the episode index "
                    f"lists length {entry.length}"
                )
            if rows[-1] - rows[0] + 1 != rows.size:
                raise DatasetError(
                    f"{self.path}: episode {entry.index}: key 'episode_index': its frames are not consecutive rows"
                )

    def episode(self, entry: EpisodeEntry) -> Episode:
        """One episode's values, after its frame indices, timestamps and task indices are checked."""
        rows = np.flatnonzero(self.episode_ids == entry.index)
        start, stop = int(rows[0]), int(rows[-1]) + 1
        where = f"{self.path}: episode {entry.index}"
        frame_index = self._integers("frame_index")[start:stop]
        wrong = np.flatnonzero(frame_index != np.arange(stop - start))
        if wrong.size:
            step = int(wrong[0])
            raise DatasetError(
                f"{where}: key 'frame_index': step {step}: value={int(frame_index[step])}: expected {step} "
                "(frames 0, 1, ..., T-1 in order)"
            )
        times = self._check_timestamps(where, start, stop)
        task_index = self._integers("task_index")[start:stop]
        unknown = [int(value) for value in np.unique(task_index) if int(value) not in self.meta.tasks]
        if unknown:
            step = int(np.flatnonzero(task_index == unknown[0])[0])
            raise DatasetError(f"{where}: key 'task_index': step {step}: value={unknown[0]}: not in the task table")
        values = {}
        for key, feature in self.columns.items():
            array = self.values(feature)[start:stop]
            check_stored_dtype(array, f"{where}: key '{feature.name}'")
            values[key] = array
        for camera, feature in self.videos.items():
            video, start_s = entry.videos[feature.name]
            label = f"episode {entry.index}: key '{feature.name}'"
            # Frame t is shown at the episode's start in the file plus its timestamp, measured from the first frame.
            offsets = times - times[0]
            values[image_key(camera)] = decode_episode(
                self.meta.root / video, start_s + times[0], offsets, feature.shape, self.image_size, label
            )
        actions = values.pop(ACTION)
        rewards, dones, states = values.pop(REWARD, None), values.pop(DONE, None), values.pop(SIM_STATE, None)
        if self.adapter is not None:
            sources = {name: values.pop(SOURCE_PREFIX + name) for name in self.adapter.sources}
            derived = self.adapter.derive(sources, where)
            values.update(derived.obs)
            states = derived.states if states is None else states
        attrs = {
            **self._carp_attrs(entry.index),
            "lerobot_episode_index": entry.index,
            "lerobot_tasks": json.dumps(list(entry.tasks)),
        }
        return Episode(
            obs=values,
            actions=actions,
            states=states,
            rewards=None if rewards is None else rewards[:, 0],
            dones=None if dones is None else dones[:, 0].astype(np.int64),
            attrs=attrs,
        )

    def _check_timestamps(self, where: str, start: int, stop: int) -> np.ndarray:
        """The episode's (T,) timestamps in seconds, checked to advance by 1 / fps."""
        if "timestamp" not in self.converted:
            column = self._column("timestamp")
            if not pa.types.is_floating(column.type):
                raise DatasetError(f"{self.path}: key 'timestamp': type={column.type}: expected seconds (floats)")
            self.converted["timestamp"] = column.to_numpy(zero_copy_only=False).astype(np.float64)
        times = self.converted["timestamp"][start:stop]
        period = 1.0 / self.meta.fps
        gaps = np.diff(times)
        wrong = np.flatnonzero(~(np.abs(gaps - period) <= TIMESTAMP_TOLERANCE_S))
        if wrong.size:
            step = int(wrong[0]) + 1
            raise DatasetError(
                f"{where}: key 'timestamp': step {step}: value={times[step]:.6g} s follows {times[step - 1]:.6g} s, "
                f"a gap of {gaps[step - 1]:.6g} s where fps={self.meta.fps:g} needs {period:.6g} s "
                "(a dropped, repeated or misordered frame)"
            )
        return times

    def _carp_attrs(self, episode_index: int) -> dict:
        attrs = _carp_object(self.meta, "episode_attrs").get(str(episode_index), {})
        if not isinstance(attrs, dict):
            raise DatasetError(f"{self.meta.root / 'meta/carp.json'}: episode {episode_index}: expected an object")
        return attrs


def _dtype_name(kind: pa.DataType) -> str:
    if pa.types.is_boolean(kind):
        return "bool"
    try:
        return np.dtype(kind.to_pandas_dtype()).name
    except (NotImplementedError, TypeError):
        return str(kind)
