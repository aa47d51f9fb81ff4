"""LeRobotDataset folders (Hugging Face LeRobot's dataset format) as carp demonstrations, read and written with pyarrow.

Layouts, as LeRobot's ``lerobot.datasets`` package writes them (codebase versions v3.0 and v2.0/v2.1)::

    v3.0
    meta/info.json                        codebase_version, fps, features, data_path, totals, splits
    meta/stats.json                       per-feature statistics (written on export; carp fits its own on ingest)
    meta/tasks.parquet                    one row per task: task_index, the task text as the pandas index
    meta/episodes/chunk-*/file-*.parquet  one row per episode: episode_index, length, tasks, data/chunk_index,
                                          data/file_index, dataset_from_index, dataset_to_index
    data/chunk-*/file-*.parquet           the frames of several episodes; an episode lies in one file

    v2.0, v2.1
    meta/info.json                        as above; data_path names one file per episode, chunks_size episodes a chunk
    meta/episodes.jsonl                   {"episode_index", "tasks", "length"} per line
    meta/tasks.jsonl                      {"task_index", "task"} per line
    data/chunk-*/episode_*.parquet        the frames of one episode

A frame row holds one column per feature of ``info.json`` (a number for shape ``(1,)``, a list of ``D`` numbers for
``(D,)``) and LeRobot's bookkeeping columns ``timestamp``, ``frame_index``, ``episode_index``, ``index`` and
``task_index``. Camera features (dtype ``video`` or ``image``) live in MP4 or PNG files beside the tables.

carp's side (:mod:`carp.data.lerobot.reader`, :mod:`carp.data.lerobot.writer`): an obs key ``k`` of ``data.obs_keys``
names the feature ``k`` or ``observation.k`` (``state`` reads ``observation.state``), ``action`` holds the actions,
``next.reward`` and ``next.done`` the rewards and done flags, and ``sim_state`` the simulator states that carp renders
camera images from, and a camera ``c`` of an image run the video feature ``observation.images.c``
(:mod:`carp.data.lerobot.videos`). carp's own export adds ``meta/carp.json`` (the env_args and per-demo attributes of
the robomimic file), which LeRobot ignores. Deviations from LeRobot: PNG image features are not read, the export
writes no camera, and ``meta/stats.json`` is never read.
"""

from pathlib import Path

# The file whose presence marks a folder as a LeRobotDataset (every codebase version has it).
INFO_PATH = Path("meta/info.json")


def is_lerobot_dataset(path: Path) -> bool:
    """Whether ``path`` is a folder holding ``meta/info.json``."""
    return Path(path).is_dir() and (Path(path) / INFO_PATH).is_file()
