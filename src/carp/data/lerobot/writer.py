"""Write carp demonstrations as a LeRobotDataset v3.0 folder (layout in :mod:`carp.data.lerobot`).

Features written, per frame of a demo with T steps:

- ``observation.state``: the ``state_keys`` concatenated, the vector LeRobot's policies read;
- ``observation.<key>``: every low-dim obs key of the demos, on its own, so that carp's ``data.obs_keys`` read the
  export as they read the robomimic file;
- ``action``: the actions as stored (absolute 7-D for carp's arm tasks, 2-D for Push-T);
- ``sim_state``: the simulator states (when the demos have them), which carp renders camera images from;
- ``next.reward``, ``next.done``; and LeRobot's ``timestamp`` (frame_index / fps), ``frame_index``, ``episode_index``,
  ``index``, ``task_index``;
- ``observation.images.<camera>``: the camera images the demos store (obs keys ``<camera>_image``), as MP4 video with
  LeRobot's own encoder settings (:func:`carp.data.lerobot.videos.encode_video`), one file per camera beside each
  data file, the episodes one after another.

Numbers are stored as float64, the dtype carp reads them in, so an export read back gives the same values bit for
bit (camera images are compressed, so they come back within a few levels). ``meta/carp.json`` keeps the env_args and
the per-demo attributes (seeds, model files) that LeRobot has no place for, and robomimic's masks become
``info.json``'s ``splits`` (ranges of consecutive episodes, as LeRobot writes them).
Each data file holds at most ``episodes_per_file`` whole episodes, as LeRobot keeps an episode in one file.
LeRobot's own statistics (``meta/stats.json``: min, max, mean, std, count) are computed over all frames.
"""

import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from carp.data.lerobot.metadata import CARP_PATH, EPISODES_DIR, INFO_PATH, TASKS_PATH, V3
from carp.data.lerobot.reader import ACTION, DONE, OBSERVATION_PREFIX, REWARD, SIM_STATE
from carp.data.lerobot.videos import IMAGE_PREFIX, encode_video, video_info
from carp.data.robomimic_io import Demonstrations
from carp.data.robomimic_schema import IMAGE_KEY_SUFFIX, DatasetError, is_image_key
from carp.data.staging import staged

STATE = OBSERVATION_PREFIX + "state"
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = str(EPISODES_DIR / "chunk-000/file-000.parquet")
# LeRobot's defaults for the shard settings recorded in info.json.
CHUNKS_SIZE = 1000
DATA_FILES_SIZE_IN_MB = 100
VIDEO_FILES_SIZE_IN_MB = 200
STORED_DTYPE = "float64"


def write_lerobot_dataset(
    demos: Demonstrations,
    output: Path,
    fps: int,
    state_keys: Sequence[str],
    task_text: str,
    staging_dir: Path | None = None,
    episodes_per_file: int = 1000,
) -> None:
    """Write ``demos`` as a LeRobotDataset v3.0 folder at ``output``, replacing it atomically.

    Args:
        demos: demos as :func:`carp.data.robomimic_io.read_demonstrations` returns them: low-dim obs (T, D) float,
            camera images ``<camera>_image`` (T, H, W, 3) uint8 with H and W even; episode ``i`` of the export is
            ``demos.episodes[i]``.
        output: the dataset folder; replaced only once completely written.
        fps: frames per second, the task's control rate.
        state_keys: obs keys concatenated, in this order, into ``observation.state``.
        task_text: the task every episode records.
        staging_dir: where the folder is built before its rename (see :mod:`carp.data.staging`); ``None`` uses
            ``output``'s parent.
        episodes_per_file: whole episodes per data file.

    Raises:
        DatasetError: a state key the demos lack, or a mask whose demos are not consecutive (info.json's splits hold
            ranges).
    """
    output = Path(output)
    first = demos.episodes[0]
    for key in state_keys:
        if key not in first.obs:
            raise DatasetError(f"{demos.path}: obs key '{key}': not among the demos' obs keys {sorted(first.obs)}")
    splits = _splits(demos)
    columns = [_frame_columns(demos, index, state_keys, fps) for index in range(len(demos.episodes))]
    cameras = _cameras(demos)
    features = _features(columns[0], state_keys, demos)
    for camera, shape in cameras.items():
        features[IMAGE_PREFIX + camera] = {
            "dtype": "video",
            "shape": list(shape),
            "names": ["height", "width", "channels"],
            "info": video_info(shape, fps),
        }
    output.parent.mkdir(parents=True, exist_ok=True)
    with staged(staging_dir or output.parent, output.name) as staging:
        staging.mkdir()
        episode_rows = _write_data(staging, columns, task_text, episodes_per_file)
        _write_videos(staging, demos, cameras, episode_rows, episodes_per_file, fps)
        _write_table(staging / EPISODES_PATH, pa.Table.from_pylist(episode_rows))
        (staging / TASKS_PATH).parent.mkdir(parents=True, exist_ok=True)
        pd.DataFrame({"task_index": [0]}, index=[task_text]).to_parquet(staging / TASKS_PATH)
        info = {
            "codebase_version": V3,
            "robot_type": None,
            "total_episodes": len(columns),
            "total_frames": int(sum(len(frame["frame_index"]) for frame in columns)),
            "total_tasks": 1,
            "chunks_size": CHUNKS_SIZE,
            "data_files_size_in_mb": DATA_FILES_SIZE_IN_MB,
            "video_files_size_in_mb": VIDEO_FILES_SIZE_IN_MB,
            "fps": int(fps),
            "splits": splits,
            "data_path": DATA_PATH,
            "video_path": VIDEO_PATH if cameras else None,
            "features": features,
        }
        _write_json(staging / INFO_PATH, info)
        _write_json(staging / "meta/stats.json", {**_stats(columns, features), **_image_stats(demos, cameras)})
        _write_json(staging / CARP_PATH, _carp_record(demos))
        if output.exists():
            shutil.rmtree(output)
        os.replace(staging, output)


def _frame_columns(demos: Demonstrations, index: int, state_keys: Sequence[str], fps: int) -> dict[str, np.ndarray]:
    """Feature -> (T, D) values of one episode, plus the bookkeeping columns (T,)."""
    episode = demos.episodes[index]
    steps = episode.length
    columns = {STATE: np.concatenate([episode.obs[key] for key in state_keys], axis=1)}
    for key, values in episode.obs.items():
        if not is_image_key(key):
            columns[OBSERVATION_PREFIX + key] = values.reshape(steps, -1)
    columns[ACTION] = episode.actions
    if episode.states is not None and episode.states.size:
        columns[SIM_STATE] = episode.states.reshape(steps, -1)
    if episode.rewards is not None:
        columns[REWARD] = episode.rewards.reshape(steps, 1)
    if episode.dones is not None:
        columns[DONE] = episode.dones.reshape(steps, 1).astype(bool)
    frame_index = np.arange(steps, dtype=np.int64)
    columns["timestamp"] = (frame_index / fps).astype(np.float32)
    columns["frame_index"] = frame_index
    columns["episode_index"] = np.full(steps, index, dtype=np.int64)
    return columns


def _features(columns: dict[str, np.ndarray], state_keys: Sequence[str], demos: Demonstrations) -> dict:
    first = demos.episodes[0]
    features = {}
    for name, values in columns.items():
        if name in ("timestamp", "frame_index", "episode_index"):
            continue
        dtype = "bool" if name == DONE else STORED_DTYPE
        names = None
        if name == STATE:
            names = [
                f"{key}_{i}" for key in state_keys for i in range(first.obs[key].reshape(first.length, -1).shape[1])
            ]
        features[name] = {"dtype": dtype, "shape": [int(values.shape[1])], "names": names}
    features["timestamp"] = {"dtype": "float32", "shape": [1], "names": None}
    for name in ("frame_index", "episode_index", "index", "task_index"):
        features[name] = {"dtype": "int64", "shape": [1], "names": None}
    return features


def _cameras(demos: Demonstrations) -> dict[str, tuple[int, int, int]]:
    """Camera -> (H, W, 3) of the images the demos store; DatasetError for a size the video cannot hold."""
    cameras = {}
    for key, images in demos.episodes[0].obs.items():
        if not is_image_key(key):
            continue
        shape = tuple(int(size) for size in images.shape[1:])
        if shape[0] % 2 or shape[1] % 2:
            raise DatasetError(
                f"{demos.path}: obs key '{key}': image size {shape[0]} x {shape[1]}: MP4 video (4:2:0) needs an even "
                "height and width"
            )
        cameras[key[: -len(IMAGE_KEY_SUFFIX)]] = shape
    return cameras


def _write_videos(
    root: Path, demos: Demonstrations, cameras: dict, episode_rows: list[dict], episodes_per_file: int, fps: int
) -> None:
    """One MP4 file per camera beside each data file, its episodes one after another; adds the rows' video columns."""
    for camera in cameras:
        key = IMAGE_PREFIX + camera
        for first in range(0, len(demos.episodes), episodes_per_file):
            rows = episode_rows[first : first + episodes_per_file]
            chunk, file = rows[0]["data/chunk_index"], rows[0]["data/file_index"]
            episodes = demos.episodes[first : first + episodes_per_file]
            frames = np.concatenate([episode.obs[f"{camera}{IMAGE_KEY_SUFFIX}"] for episode in episodes])
            encode_video(root / VIDEO_PATH.format(video_key=key, chunk_index=chunk, file_index=file), frames, fps)
            start = 0
            for row, episode in zip(rows, episodes, strict=True):
                row[f"videos/{key}/chunk_index"] = chunk
                row[f"videos/{key}/file_index"] = file
                row[f"videos/{key}/from_timestamp"] = start / fps
                row[f"videos/{key}/to_timestamp"] = (start + episode.length) / fps
                start += episode.length


def _image_stats(demos: Demonstrations, cameras: dict) -> dict:
    """LeRobot's per-channel statistics of each camera, in [0, 1] and shaped (3, 1, 1) as its loader expects."""
    stats = {}
    for camera in cameras:
        pixels = np.concatenate([e.obs[f"{camera}{IMAGE_KEY_SUFFIX}"].reshape(-1, 3) for e in demos.episodes]) / 255.0
        stats[IMAGE_PREFIX + camera] = {
            name: [[[float(value)]] for value in values]
            for name, values in (
                ("min", pixels.min(axis=0)),
                ("max", pixels.max(axis=0)),
                ("mean", pixels.mean(axis=0)),
                ("std", pixels.std(axis=0)),
            )
        } | {"count": [int(pixels.shape[0])]}
    return stats


def _write_data(root: Path, columns: list[dict[str, np.ndarray]], task_text: str, episodes_per_file: int) -> list:
    """Write the data files; returns one episode-index row per episode."""
    rows, start = [], 0
    for file_number, first in enumerate(range(0, len(columns), episodes_per_file)):
        chunk, file = divmod(file_number, CHUNKS_SIZE)
        group = columns[first : first + episodes_per_file]
        arrays = {}
        for name in group[0]:
            values = np.concatenate([episode[name] for episode in group])
            arrays[name] = _arrow_column(name, values)
        steps = sum(len(episode["frame_index"]) for episode in group)
        arrays["index"] = pa.array(np.arange(start, start + steps, dtype=np.int64))
        arrays["task_index"] = pa.array(np.zeros(steps, dtype=np.int64))
        _write_table(root / DATA_PATH.format(chunk_index=chunk, file_index=file), pa.table(arrays))
        for episode in group:
            length = len(episode["frame_index"])
            rows.append(
                {
                    "episode_index": int(episode["episode_index"][0]),
                    "tasks": [task_text],
                    "length": length,
                    "data/chunk_index": chunk,
                    "data/file_index": file,
                    "dataset_from_index": start,
                    "dataset_to_index": start + length,
                    "meta/episodes/chunk_index": 0,
                    "meta/episodes/file_index": 0,
                }
            )
            start += length
    return rows


def _arrow_column(name: str, values: np.ndarray) -> pa.Array:
    """A (N,) column as numbers, a (N, D) one as fixed-size lists of D, the types LeRobot's own writer uses."""
    if values.ndim == 1:
        return pa.array(values)
    if values.shape[1] == 1 and name != STATE:
        return pa.array(values[:, 0])
    flat = pa.array(values.reshape(-1))
    return pa.FixedSizeListArray.from_arrays(flat, int(values.shape[1]))


def _write_table(path: Path, table: pa.Table) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path)


def _stats(columns: list[dict[str, np.ndarray]], features: dict) -> dict:
    stats = {}
    for name in features:
        if name not in columns[0] or name == DONE:
            continue
        values = np.concatenate([episode[name] for episode in columns]).astype(np.float64)
        values = values.reshape(values.shape[0], -1)
        stats[name] = {
            "min": values.min(axis=0).tolist(),
            "max": values.max(axis=0).tolist(),
            "mean": values.mean(axis=0).tolist(),
            "std": values.std(axis=0).tolist(),
            "count": [int(values.shape[0])],
        }
    return stats


def _splits(demos: Demonstrations) -> dict[str, str]:
    position = {name: index for index, name in enumerate(demos.names)}
    splits = {}
    for key, names in demos.masks.items():
        indices = sorted(position[name] for name in names if name in position)
        if not indices:
            continue
        if indices != list(range(indices[0], indices[-1] + 1)):
            raise DatasetError(
                f"{demos.path}: mask 'mask/{key}': its demos are not consecutive; LeRobot's splits hold ranges "
                "'start:end' of episodes"
            )
        splits[key] = f"{indices[0]}:{indices[-1] + 1}"
    return splits


def _carp_record(demos: Demonstrations) -> dict:
    return {
        "env_args": demos.env_args,
        "attrs": {key: _jsonable(value) for key, value in demos.attrs.items()},
        "episode_attrs": {
            str(index): {key: _jsonable(value) for key, value in episode.attrs.items()}
            for index, episode in enumerate(demos.episodes)
        },
    }


def _jsonable(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def _write_json(path: Path, value: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(value, indent=4) + "\n")
