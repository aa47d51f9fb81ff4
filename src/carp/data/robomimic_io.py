"""Read and write demonstration files in the robomimic HDF5 schema.

Schema (robomimic's ``dataset_states_to_obs`` output)::

    data/                     attrs: env_args (JSON: env_name, env_version, type, env_kwargs), total
    data/demo_<i>/            attrs: num_samples (T), optional model_file
    data/demo_<i>/obs/<key>   (T, ...) observations; camera images <camera>_image are uint8 (T, H, W, 3)
    data/demo_<i>/actions     (T, action_dim)
    data/demo_<i>/states      (T, S) flattened mujoco states
    data/demo_<i>/rewards     (T,)
    data/demo_<i>/dones       (T,)
    mask/<filter>             list of demo names (bytes), e.g. mask/train, mask/valid

Any file in this schema is accepted, ours (scripted experts) or a user's robomimic download. Validation
(:mod:`carp.data.robomimic_schema`) raises :class:`DatasetError` with a one-line message naming the file, the demo
and the key.
"""

import json
import os
import re
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from carp.data.robomimic_schema import (
    OPTIONAL_KEYS,
    DatasetError,
    check_demo_layout,
    check_same_widths,
    check_stored_ranges,
    check_valid_mask,
    hdf5_errors,
    is_image_key,
    open_hdf5,
    read_images,
    read_masks,
    read_values,
    require_group,
)
from carp.data.staging import staged


@dataclass
class Episode:
    """One demonstration.

    Attributes:
        obs: observation key -> array: (T, D_key) float for low-dimensional keys, (T, H, W, 3) uint8 for camera
            images (keys ending in ``_image``).
        actions: (T, action_dim) float actions as the controller received them.
        states: (T, S) simulator states (may be empty (T, 0) when unknown).
        rewards: (T,) rewards.
        dones: (T,) done flags.
        attrs: extra per-demo attributes (e.g. the seed it was collected with).
    """

    obs: dict[str, np.ndarray]
    actions: np.ndarray
    states: np.ndarray | None = None
    rewards: np.ndarray | None = None
    dones: np.ndarray | None = None
    attrs: dict = field(default_factory=dict)

    @property
    def length(self) -> int:
        """Number of steps T."""
        return int(self.actions.shape[0])


@dataclass
class Demonstrations:
    """The demos of one file, in file order (demo_0, demo_1, ... sorted numerically)."""

    path: Path
    env_args: dict
    names: list[str]
    episodes: list[Episode]
    attrs: dict
    masks: dict[str, list[str]] = field(default_factory=dict)


def _demo_sort_key(name: str) -> tuple[int, str]:
    match = re.fullmatch(r"demo_(\d+)", name)
    return (int(match.group(1)) if match else 1 << 60, name)


def write_demonstrations(
    path: Path,
    episodes: Sequence[Episode],
    env_args: dict,
    file_attrs: dict | None = None,
    valid_fraction: float = 0.1,
    staging_dir: Path | None = None,
    names: Sequence[str] | None = None,
    masks: dict[str, list[str]] | None = None,
) -> None:
    """Write episodes as a robomimic-schema file, atomically (temp file, then rename).

    Args:
        path: destination ``.hdf5``; never left half-written.
        episodes: demonstrations, stored as ``demo_0 .. demo_{N-1}``.
        env_args: JSON-serializable dict that recreates the env (``env_name``, ``env_kwargs``, ...).
        file_attrs: extra attributes stored on the ``data`` group (JSON-encoded when not scalar).
        valid_fraction: share of demos (the last ones, at least one when N >= 2) listed in ``mask/valid``;
            the rest go to ``mask/train``.
        staging_dir: where the file is built before its rename (see :mod:`carp.data.staging`); ``None`` uses
            ``path``'s folder.
        names: the demos' names, one per episode; ``None`` names them ``demo_0 .. demo_{N-1}``.
        masks: ``mask/<name>`` lists of demo names written as given instead of the ``valid_fraction`` split
            (``{}`` writes no mask).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = list(names) if names is not None else [f"demo_{index}" for index in range(len(episodes))]
    if masks is None:
        num_valid = 0 if len(names) < 2 else max(1, int(round(valid_fraction * len(names))))
        split = len(names) - num_valid
        masks = {"train": names[:split], "valid": names[split:]}
    with staged(staging_dir or path.parent, path.name) as temporary:
        with h5py.File(temporary, "w") as handle:
            data = handle.create_group("data")
            data.attrs["env_args"] = json.dumps(env_args)
            data.attrs["total"] = int(sum(episode.length for episode in episodes))
            for key, value in (file_attrs or {}).items():
                data.attrs[key] = value if isinstance(value, (int, float, str)) else json.dumps(value)
            for name, episode in zip(names, episodes, strict=True):
                group = data.create_group(name)
                group.attrs["num_samples"] = episode.length
                for key, value in episode.attrs.items():
                    group.attrs[key] = value
                for key, value in episode.obs.items():
                    group.create_dataset(f"obs/{key}", data=value)
                group.create_dataset("actions", data=episode.actions)
                steps = episode.length
                group.create_dataset(
                    "states", data=episode.states if episode.states is not None else np.zeros((steps, 0))
                )
                group.create_dataset(
                    "rewards", data=episode.rewards if episode.rewards is not None else np.zeros(steps)
                )
                group.create_dataset(
                    "dones", data=episode.dones if episode.dones is not None else np.zeros(steps, dtype=np.int64)
                )
            for key, listed in masks.items():
                handle.create_dataset(f"mask/{key}", data=np.array(listed, dtype="S"))
        os.replace(temporary, path)


def read_demonstrations(
    path: Path,
    obs_keys: Sequence[str],
    action_dim: int | None = None,
    filter_key: str | None = None,
    env_name: str | None = None,
) -> Demonstrations:
    """Read and validate the demos of a robomimic-schema file (checks in :mod:`carp.data.robomimic_schema`).

    Args:
        path: the ``.hdf5`` file.
        obs_keys: observation keys to load from every demo's ``obs`` group.
        action_dim: expected action width; ``None`` accepts any.
        filter_key: name under ``mask/`` selecting a subset of demos; ``None`` reads all.
        env_name: the ``env_name`` its ``env_args`` must name (the task's environment); ``None`` accepts any.

    Raises:
        DatasetError: one line naming the file, demo and key for every schema or value problem.
    """
    path = Path(path)
    with open_hdf5(path) as handle, hdf5_errors(str(path)):
        data = require_group(handle, "data", f"{path}: group 'data'")
        env_args = _read_env_args(path, data)
        check_env_name(path, env_args, env_name)
        all_names = sorted((name for name in data.keys() if name.startswith("demo")), key=_demo_sort_key)
        masks = read_masks(handle, path, all_names)
        names = select_demos(path, all_names, masks, filter_key)
        check_valid_mask(path, names, masks, filter_key)
        groups = [require_group(data, name, f"{path}: demo '{name}'") for name in names]
        layouts = [
            check_demo_layout(group, f"{path}: demo '{name}'", obs_keys, action_dim)
            for name, group in zip(names, groups, strict=True)
        ]
        check_same_widths(path, names, layouts)
        episodes = [_read_episode(group, f"{path}: demo '{name}'", obs_keys) for name, group in zip(names, groups)]
        check_stored_ranges(path, names, "key 'actions'", [episode.actions for episode in episodes])
        for key in obs_keys:
            if not is_image_key(key):
                check_stored_ranges(path, names, f"obs key '{key}'", [episode.obs[key] for episode in episodes])
        attrs = {key: _decode_attr(value) for key, value in data.attrs.items() if key != "env_args"}
    return Demonstrations(path=path, env_args=env_args, names=names, episodes=episodes, attrs=attrs, masks=masks)


def import_demonstrations(
    source: Path,
    destination: Path,
    obs_keys: Sequence[str],
    action_dim: int | None = None,
    filter_key: str | None = None,
    staging_dir: Path | None = None,
    env_name: str | None = None,
) -> Demonstrations:
    """Validate a user's file as :func:`read_demonstrations` does, then copy it to ``destination`` atomically.

    Args:
        source: the user's robomimic-schema file; every message names it.
        destination: replaced only once ``source`` passed every check and was copied completely.
        obs_keys: observation keys every demo must have.
        action_dim: expected action width; ``None`` accepts any.
        filter_key: ``mask/<filter_key>`` the file must hold; ``None`` checks all demos.
        staging_dir: where the copy is built before its rename (see :mod:`carp.data.staging`); ``None`` uses
            ``destination``'s folder.
        env_name: the ``env_name`` its ``env_args`` must name; ``None`` accepts any.

    Raises:
        DatasetError: ``source`` breaks the schema; ``destination`` is left as it was.
        OSError: the copy failed (e.g. a full disk); ``destination`` is left as it was.
    """
    demos = read_demonstrations(source, obs_keys, action_dim=action_dim, filter_key=filter_key, env_name=env_name)
    destination = Path(destination)
    with staged(staging_dir or destination.parent, destination.name) as temporary:
        shutil.copyfile(source, temporary)
        destination.parent.mkdir(parents=True, exist_ok=True)
        os.replace(temporary, destination)
    return demos


def check_env_name(path: Path, env_args: dict, env_name: str | None) -> None:
    """Refuse a file whose ``env_args`` name another env than ``env_name`` (None accepts any), naming both."""
    if env_name is not None and env_args.get("env_name") != env_name:
        raise DatasetError(
            f"{path}: data.attrs['env_args'] env_name={env_args.get('env_name')!r}: this task's demos come from "
            f"{env_name!r}"
        )


def read_env_args(path: Path) -> dict:
    """The ``env_args`` a robomimic-schema file records, without reading its demos.

    Raises:
        DatasetError: an unreadable file or a missing or malformed ``env_args``, naming the file.
    """
    path = Path(path)
    with open_hdf5(path) as handle, hdf5_errors(str(path)):
        return _read_env_args(path, require_group(handle, "data", f"{path}: group 'data'"))


def _read_env_args(path: Path, data: h5py.Group) -> dict:
    if "env_args" not in data.attrs:
        raise DatasetError(f"{path}: group 'data' has no attribute 'env_args'")
    raw = data.attrs["env_args"]
    try:
        env_args = json.loads(raw)
    except (json.JSONDecodeError, TypeError, UnicodeDecodeError) as error:
        raise DatasetError(f"{path}: data.attrs['env_args']={_short(raw)}: not JSON ({error})") from None
    if not isinstance(env_args, dict):
        raise DatasetError(f"{path}: data.attrs['env_args']={_short(raw)}: expected a JSON object")
    return env_args


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else f"{text[:57]}..."


def select_demos(path: Path, names: list[str], masks: dict[str, list[str]], filter_key: str | None) -> list[str]:
    """The demos ``mask/<filter_key>`` lists (all ``names`` when None); DatasetError for a missing mask or none."""
    if filter_key is not None:
        if filter_key not in masks:
            raise DatasetError(f"{path}: filter key 'mask/{filter_key}' not found (masks: {sorted(masks)})")
        names = sorted(masks[filter_key], key=_demo_sort_key)
    if not names:
        where = f"filter key 'mask/{filter_key}' lists" if filter_key is not None else "group 'data' holds"
        raise DatasetError(f"{path}: {where} no demos")
    return names


def _decode_attr(value):
    if isinstance(value, bytes):
        value = value.decode(errors="replace")  # informational attributes: a bad byte must not refuse the file
    if isinstance(value, np.generic):
        return value.item()
    return value


def _read_episode(group: h5py.Group, where: str, obs_keys: Sequence[str]) -> Episode:
    """Values of a demo whose layout :func:`check_demo_layout` accepted."""
    actions = read_values(group["actions"], f"{where}: key 'actions'")
    obs = {}
    for key in obs_keys:
        label = f"{where}: obs key '{key}'"
        if is_image_key(key):
            obs[key] = read_images(group[f"obs/{key}"], label)
            continue
        values = read_values(group[f"obs/{key}"], label)
        obs[key] = values.reshape(values.shape[0], -1)
    with hdf5_errors(where):
        optional = {key: group[key][()] if key in group else None for key in OPTIONAL_KEYS}
        attrs = {key: _decode_attr(value) for key, value in group.attrs.items()}
    return Episode(obs=obs, actions=actions, attrs=attrs, **optional)


def read_obs_keys(path: Path) -> list[str]:
    """The obs keys of a robomimic-schema file's first demo (``data/demo_<i>/obs/<key>``), sorted.

    Raises:
        DatasetError: an unreadable file, no demo, or a first demo without an ``obs`` group, naming the file.
    """
    path = Path(path)
    with open_hdf5(path) as handle, hdf5_errors(str(path)):
        data = require_group(handle, "data", f"{path}: group 'data'")
        names = sorted((name for name in data.keys() if name.startswith("demo")), key=_demo_sort_key)
        if not names:
            raise DatasetError(f"{path}: group 'data' holds no demos")
        obs = require_group(data, f"{names[0]}/obs", f"{path}: demo '{names[0]}': group 'obs'")
        return sorted(obs.keys())
