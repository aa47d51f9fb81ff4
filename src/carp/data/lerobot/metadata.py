"""The ``meta/`` folder of a LeRobotDataset (layouts in :mod:`carp.data.lerobot`): info, episode index and tasks.

Every check raises :class:`~carp.data.robomimic_schema.DatasetError` with one line naming the file, the episode and the
key, before any frame is read.
"""

import json
import math
import string
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from carp.data.lerobot import INFO_PATH
from carp.data.robomimic_schema import DatasetError

TASKS_PATH = Path("meta/tasks.parquet")
EPISODES_DIR = Path("meta/episodes")
LEGACY_EPISODES_PATH = Path("meta/episodes.jsonl")
LEGACY_TASKS_PATH = Path("meta/tasks.jsonl")
# carp's own record beside LeRobot's metadata (env_args, per-demo attributes, the robomimic masks); LeRobot ignores it.
CARP_PATH = Path("meta/carp.json")

V3 = "v3.0"
LEGACY_VERSIONS = ("v2.0", "v2.1")
VERSIONS = (V3, *LEGACY_VERSIONS)
# Numbers a low-dimensional feature may hold (LeRobot's feature dtypes are numpy dtype names).
NUMERIC_DTYPES = ("float16", "float32", "float64", "int8", "int16", "int32", "int64", "uint8", "bool")
CAMERA_DTYPES = ("video", "image")
# The fields each layout's data_path template may name (str.format); anything else is refused before formatting.
DATA_PATH_FIELDS = {V3: {"chunk_index", "file_index"}, "legacy": {"episode_chunk", "episode_index"}}
VIDEO_PATH_FIELDS = {
    V3: {"video_key", "chunk_index", "file_index"},
    "legacy": {"episode_chunk", "video_key", "episode_index"},
}


@dataclass(frozen=True)
class Feature:
    """One entry of ``info.json``'s ``features``: a numpy dtype name (or ``video``/``image``) and a per-frame shape."""

    name: str
    dtype: str
    shape: tuple[int, ...]


@dataclass(frozen=True)
class EpisodeEntry:
    """One episode of the index.

    Attributes:
        index: its ``episode_index``.
        length: frames T the index lists.
        tasks: the task texts it records.
        data_file: the Parquet file holding its frames, relative to the dataset root.
        videos: video feature -> (its MP4 file relative to the root, the episode's start time in it in seconds).
    """

    index: int
    length: int
    tasks: tuple[str, ...]
    data_file: Path
    videos: dict[str, tuple[Path, float]]


@dataclass(frozen=True)
class Metadata:
    """What ``meta/`` says about a dataset.

    Attributes:
        root: the dataset folder.
        version: ``codebase_version``.
        fps: frames per second; consecutive timestamps of an episode differ by 1 / fps.
        features: name -> feature.
        episodes: the episode index, sorted by ``episode_index``.
        tasks: task_index -> task text.
        splits: split name -> episode indices (``info.json``'s ``"a:b"`` ranges).
        carp: the content of ``meta/carp.json``, ``{}`` when absent.
    """

    root: Path
    version: str
    fps: float
    features: dict[str, Feature]
    episodes: list[EpisodeEntry]
    tasks: dict[int, str]
    splits: dict[str, list[int]]
    carp: dict


def read_metadata(root: Path) -> Metadata:
    """Read and check ``meta/``: info, episode index, tasks, splits and carp's own record.

    Raises:
        DatasetError: a missing or malformed file, an unsupported version, a feature without dtype or shape, an
            episode listed twice or with a non-positive length, an episode's task unknown to the task table, totals
            that contradict the index, or a split naming an episode the index lacks.
    """
    root = Path(root)
    info_file = root / INFO_PATH
    info = _read_json_object(info_file)
    version = _require(info, "codebase_version", str, info_file)
    if version not in VERSIONS:
        raise DatasetError(f"{info_file}: key 'codebase_version'={version!r}: carp reads LeRobot {list(VERSIONS)}")
    fps = _require(info, "fps", (int, float), info_file)
    if isinstance(fps, bool) or not math.isfinite(fps) or fps <= 0:
        raise DatasetError(f"{info_file}: key 'fps'={fps!r}: expected a positive number of frames per second")
    features = _features(info_file, _require(info, "features", dict, info_file))
    layout = V3 if version == V3 else "legacy"
    template = _require(info, "data_path", str, info_file)
    _check_template(info_file, "data_path", template, DATA_PATH_FIELDS[layout])
    video_keys = [name for name, feature in features.items() if feature.dtype == "video"]
    video_template = _require(info, "video_path", str, info_file) if video_keys else ""
    _check_template(info_file, "video_path", video_template, VIDEO_PATH_FIELDS[layout])
    if version == V3:
        tasks = _v3_tasks(root)
        episodes = _v3_episodes(root, template, video_template, video_keys)
    else:
        chunks_size = _require(info, "chunks_size", int, info_file)
        if chunks_size <= 0:
            raise DatasetError(f"{info_file}: key 'chunks_size'={chunks_size}: expected a positive number")
        tasks = _legacy_tasks(root)
        episodes = _legacy_episodes(root, template, chunks_size, video_template, video_keys)
    _check_episodes(root, episodes, tasks)
    _check_totals(info_file, info, episodes)
    splits = _splits(info_file, info.get("splits") or {}, {entry.index for entry in episodes})
    carp_file = root / CARP_PATH
    carp = _read_json_object(carp_file) if carp_file.exists() else {}
    return Metadata(root, version, float(fps), features, episodes, tasks, splits, carp)


def _read_json_object(path: Path) -> dict:
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    try:
        value = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DatasetError(f"{path}: cannot be read as JSON ({error})") from None
    if not isinstance(value, dict):
        raise DatasetError(f"{path}: expected a JSON object, found {type(value).__name__}")
    return value


def _require(mapping: dict, key: str, kind, where: Path):
    if key not in mapping:
        raise DatasetError(f"{where}: key '{key}': missing")
    value = mapping[key]
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise DatasetError(f"{where}: key '{key}'={value!r}: expected {_kind_name(kind)}")
    return value


def _kind_name(kind) -> str:
    kinds = kind if isinstance(kind, tuple) else (kind,)
    return " or ".join(
        {str: "text", int: "an integer", float: "a number", dict: "an object", list: "a list"}[k] for k in kinds
    )


def _features(info_file: Path, raw: dict) -> dict[str, Feature]:
    features = {}
    for name, spec in raw.items():
        where = f"{info_file}: feature '{name}'"
        if not isinstance(spec, dict):
            raise DatasetError(f"{where}: expected an object with 'dtype' and 'shape'")
        dtype, shape = spec.get("dtype"), spec.get("shape")
        if not isinstance(dtype, str):
            raise DatasetError(f"{where}: key 'dtype'={dtype!r}: expected a dtype name")
        if not isinstance(shape, list | tuple) or not all(isinstance(n, int) and n > 0 for n in shape):
            raise DatasetError(f"{where}: key 'shape'={shape!r}: expected a list of positive sizes")
        features[name] = Feature(name, dtype, tuple(shape))
    return features


def _check_template(info_file: Path, key: str, template: str, allowed: set[str]) -> None:
    try:
        fields = {field.split(".")[0].split("[")[0] for _, field, _, _ in string.Formatter().parse(template) if field}
    except ValueError as error:
        raise DatasetError(f"{info_file}: key '{key}'={template!r}: not a path template ({error})") from None
    if not fields <= allowed or ".." in Path(template).parts:
        raise DatasetError(f"{info_file}: key '{key}'={template!r}: may only name {sorted(allowed)}")


def _v3_tasks(root: Path) -> dict[int, str]:
    path = root / TASKS_PATH
    frame = _read_parquet_frame(path)
    # LeRobot keeps the task text as the pandas index; a plain "task" column is read as well.
    texts = frame["task"] if "task" in frame.columns else pd.Series(frame.index, index=frame.index)
    if "task_index" not in frame.columns:
        raise DatasetError(f"{path}: key 'task_index': column missing (columns: {list(frame.columns)})")
    return _task_table(path, list(frame["task_index"]), [str(text) for text in texts])


def _legacy_tasks(root: Path) -> dict[int, str]:
    path = root / LEGACY_TASKS_PATH
    rows = _read_json_lines(path)
    for number, row in enumerate(rows, start=1):
        for key in ("task_index", "task"):
            if key not in row:
                raise DatasetError(f"{path}: line {number}: key '{key}': missing")
    return _task_table(path, [row["task_index"] for row in rows], [str(row["task"]) for row in rows])


def _task_table(path: Path, indices: list, texts: list[str]) -> dict[int, str]:
    table = {}
    for index, text in zip(indices, texts, strict=True):
        if isinstance(index, bool) or not isinstance(index, int | np.integer):
            raise DatasetError(f"{path}: key 'task_index'={index!r}: expected an integer")
        if int(index) in table:
            raise DatasetError(f"{path}: key 'task_index'={int(index)}: listed twice")
        table[int(index)] = text
    return table


def _v3_episodes(root: Path, template: str, video_template: str, video_keys: list[str]) -> list[EpisodeEntry]:
    files = sorted((root / EPISODES_DIR).glob("chunk-*/file-*.parquet"))
    if not files:
        raise DatasetError(f"{root / EPISODES_DIR}: no episode index files (chunk-*/file-*.parquet)")
    entries = []
    for path in files:
        frame = _read_parquet_frame(path)
        video_columns = [f"videos/{key}/{part}" for key in video_keys for part in ("chunk_index", "file_index")]
        for key in ("episode_index", "length", "tasks", "data/chunk_index", "data/file_index", *video_columns):
            if key not in frame.columns:
                named = [column for column in frame.columns if not column.startswith("stats/")]
                raise DatasetError(f"{path}: key '{key}': column missing (columns besides stats/: {named})")
        for row in frame.itertuples(index=False):
            values = dict(zip(frame.columns, row, strict=True))
            index = _integer(path, values["episode_index"], "episode_index", None)
            where = f"episode {index}"
            chunk = _integer(path, values["data/chunk_index"], "data/chunk_index", where)
            file = _integer(path, values["data/file_index"], "data/file_index", where)
            length = _integer(path, values["length"], "length", where)
            tasks = _task_texts(path, values["tasks"], where)
            videos = {key: _v3_video(path, values, key, video_template, where) for key in video_keys}
            data_file = Path(template.format(chunk_index=chunk, file_index=file))
            entries.append(EpisodeEntry(index, length, tasks, data_file, videos))
    return sorted(entries, key=lambda entry: entry.index)


def _v3_video(path: Path, values: dict, key: str, template: str, where: str) -> tuple[Path, float]:
    """(MP4 file, start time in seconds) of one episode's video feature ``key`` in a v3.0 episode-index row."""
    chunk = _integer(path, values[f"videos/{key}/chunk_index"], f"videos/{key}/chunk_index", where)
    file = _integer(path, values[f"videos/{key}/file_index"], f"videos/{key}/file_index", where)
    start = values.get(f"videos/{key}/from_timestamp", 0.0)
    if isinstance(start, bool) or not isinstance(start, int | float) or not math.isfinite(start) or start < 0:
        raise DatasetError(f"{path}: {where}: key 'videos/{key}/from_timestamp'={start!r}: expected seconds >= 0")
    return Path(template.format(video_key=key, chunk_index=chunk, file_index=file)), float(start)


def _legacy_episodes(
    root: Path, template: str, chunks_size: int, video_template: str, video_keys: list[str]
) -> list[EpisodeEntry]:
    path = root / LEGACY_EPISODES_PATH
    entries = []
    for number, row in enumerate(_read_json_lines(path), start=1):
        for key in ("episode_index", "length"):
            if key not in row:
                raise DatasetError(f"{path}: line {number}: key '{key}': missing")
        index = _integer(path, row["episode_index"], "episode_index", f"line {number}")
        length = _integer(path, row["length"], "length", f"episode {index}")
        tasks = _task_texts(path, row.get("tasks", []), f"episode {index}")
        chunk = index // chunks_size
        data_file = Path(template.format(episode_chunk=chunk, episode_index=index))
        videos = {
            key: (Path(video_template.format(episode_chunk=chunk, video_key=key, episode_index=index)), 0.0)
            for key in video_keys
        }
        entries.append(EpisodeEntry(index, length, tasks, data_file, videos))
    return sorted(entries, key=lambda entry: entry.index)


def _integer(path: Path, value, key: str, where: str | None) -> int:
    prefix = f"{path}: {where}: " if where else f"{path}: "
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise DatasetError(f"{prefix}key '{key}'={value!r}: expected an integer")
    return int(value)


def _task_texts(path: Path, value, where: str) -> tuple[str, ...]:
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if not isinstance(value, list) or not all(isinstance(text, str) for text in value):
        raise DatasetError(f"{path}: {where}: key 'tasks'={value!r}: expected a list of task texts")
    return tuple(value)


def _check_episodes(root: Path, episodes: list[EpisodeEntry], tasks: dict[int, str]) -> None:
    index_file = root / (EPISODES_DIR if not (root / LEGACY_EPISODES_PATH).exists() else LEGACY_EPISODES_PATH)
    if not episodes:
        raise DatasetError(f"{index_file}: lists no episodes")
    known = set(tasks.values())
    seen = set()
    for entry in episodes:
        if entry.index in seen:
            raise DatasetError(f"{index_file}: episode {entry.index}: key 'episode_index': listed twice")
        seen.add(entry.index)
        if entry.length <= 0:
            raise DatasetError(f"{index_file}: episode {entry.index}: key 'length'={entry.length}: expected >= 1")
        unknown = [text for text in entry.tasks if text not in known]
        if unknown:
            raise DatasetError(
                f"{index_file}: episode {entry.index}: key 'tasks': {unknown[0]!r} is not in the task table"
            )


def _check_totals(info_file: Path, info: dict, episodes: list[EpisodeEntry]) -> None:
    for key, actual in (("total_episodes", len(episodes)), ("total_frames", sum(e.length for e in episodes))):
        if key in info and info[key] != actual:
            raise DatasetError(f"{info_file}: key '{key}'={info[key]!r}: the episode index lists {actual}")


def _splits(info_file: Path, raw, known: set[int]) -> dict[str, list[int]]:
    if not isinstance(raw, dict):
        raise DatasetError(f"{info_file}: key 'splits'={raw!r}: expected an object of 'start:end' ranges")
    splits = {}
    for name, value in raw.items():
        where = f"{info_file}: key 'splits.{name}'={value!r}"
        parts = value.split(":") if isinstance(value, str) else []
        if len(parts) != 2 or not all(part.strip().isdigit() for part in parts):
            raise DatasetError(f"{where}: expected a range of episode indices 'start:end'")
        start, end = int(parts[0]), int(parts[1])
        missing = sorted(set(range(start, end)) - known)
        if missing:
            raise DatasetError(f"{where}: names episode {missing[0]}, which the episode index does not list")
        splits[name] = list(range(start, end))
    return splits


def _read_json_lines(path: Path) -> list[dict]:
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    rows = []
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as error:
        raise DatasetError(f"{path}: cannot be read ({error})") from None
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError as error:
            raise DatasetError(f"{path}: line {number}: not JSON ({error})") from None
        if not isinstance(row, dict):
            raise DatasetError(f"{path}: line {number}: expected a JSON object")
        rows.append(row)
    return rows


def read_parquet_table(path: Path, columns: list[str] | None = None) -> pa.Table:
    """A Parquet file's table (only ``columns`` when given); DatasetError naming the file when it cannot be read."""
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    try:
        return pq.read_table(path, columns=columns)
    except (OSError, pa.ArrowException) as error:
        text = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise DatasetError(f"{path}: cannot be read as Parquet ({text})") from None


def _read_parquet_frame(path: Path) -> pd.DataFrame:
    return read_parquet_table(path).to_pandas()
