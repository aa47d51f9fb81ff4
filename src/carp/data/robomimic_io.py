"""Read and write demonstration files in the robomimic HDF5 schema.

Schema (robomimic's ``dataset_states_to_obs`` output)::

    data/                     attrs: env_args (JSON: env_name, env_version, type, env_kwargs), total
    data/demo_<i>/            attrs: num_samples (T), optional model_file
    data/demo_<i>/obs/<key>   (T, ...) observations
    data/demo_<i>/actions     (T, action_dim)
    data/demo_<i>/states      (T, S) flattened mujoco states
    data/demo_<i>/rewards     (T,)
    data/demo_<i>/dones       (T,)
    mask/<filter>             list of demo names (bytes), e.g. mask/train, mask/valid

Any file in this schema is accepted, ours (scripted experts) or a user's robomimic download. Validation raises
:class:`DatasetError` with a one-line message naming the file, the demo and the key.
"""

import json
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np


class DatasetError(ValueError):
    """A demonstration file that does not follow the schema or holds unusable values."""


@dataclass
class Episode:
    """One demonstration.

    Attributes:
        obs: observation key -> array (T, ...) float.
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
) -> None:
    """Write episodes as a robomimic-schema file, atomically (temp file, then rename).

    Args:
        path: destination ``.hdf5``; never left half-written.
        episodes: demonstrations, stored as ``demo_0 .. demo_{N-1}``.
        env_args: JSON-serializable dict that recreates the env (``env_name``, ``env_kwargs``, ...).
        file_attrs: extra attributes stored on the ``data`` group (JSON-encoded when not scalar).
        valid_fraction: share of demos (the last ones, at least one when N >= 2) listed in ``mask/valid``;
            the rest go to ``mask/train``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    names = [f"demo_{index}" for index in range(len(episodes))]
    num_valid = 0 if len(names) < 2 else max(1, int(round(valid_fraction * len(names))))
    try:
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
            split = len(names) - num_valid
            handle.create_dataset("mask/train", data=np.array(names[:split], dtype="S"))
            handle.create_dataset("mask/valid", data=np.array(names[split:], dtype="S"))
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def read_demonstrations(
    path: Path,
    obs_keys: Sequence[str],
    action_dim: int | None = None,
    filter_key: str | None = None,
) -> Demonstrations:
    """Read and validate the demos of a robomimic-schema file.

    Args:
        path: the ``.hdf5`` file.
        obs_keys: observation keys to load from every demo's ``obs`` group.
        action_dim: expected action width; ``None`` accepts any.
        filter_key: name under ``mask/`` selecting a subset of demos; ``None`` reads all.

    Raises:
        DatasetError: one line naming the file, demo and key for every schema or value problem.
    """
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: file not found")
    if not h5py.is_hdf5(path):
        raise DatasetError(f"{path}: not an HDF5 file")
    with h5py.File(path, "r") as handle:
        if "data" not in handle:
            raise DatasetError(f"{path}: missing group 'data'")
        data = handle["data"]
        if "env_args" not in data.attrs:
            raise DatasetError(f"{path}: group 'data' has no attribute 'env_args'")
        try:
            env_args = json.loads(data.attrs["env_args"])
        except json.JSONDecodeError as error:
            raise DatasetError(f"{path}: data.attrs['env_args'] is not JSON ({error})") from None
        names = sorted((name for name in data.keys() if name.startswith("demo")), key=_demo_sort_key)
        if filter_key is not None:
            mask_path = f"mask/{filter_key}"
            if mask_path not in handle:
                raise DatasetError(f"{path}: filter key '{mask_path}' not found")
            selected = _mask_names(handle[mask_path])
            for name in selected:
                if name not in data:
                    raise DatasetError(f"{path}: filter key '{mask_path}' names demo '{name}', which does not exist")
            names = sorted(selected, key=_demo_sort_key)
        if not names:
            raise DatasetError(f"{path}: no demos under 'data'")
        episodes = [_read_episode(path, data[name], name, obs_keys, action_dim) for name in names]
        attrs = {key: _decode_attr(value) for key, value in data.attrs.items() if key != "env_args"}
        masks = {key: _mask_names(handle[f"mask/{key}"]) for key in handle.get("mask", {}).keys()}
    return Demonstrations(path=path, env_args=env_args, names=names, episodes=episodes, attrs=attrs, masks=masks)


def _mask_names(dataset: h5py.Dataset) -> list[str]:
    return [name.decode() if isinstance(name, bytes) else str(name) for name in dataset[()]]


def _decode_attr(value):
    if isinstance(value, bytes):
        value = value.decode()
    if isinstance(value, np.generic):
        return value.item()
    return value


def _read_episode(path: Path, group: h5py.Group, name: str, obs_keys: Sequence[str], action_dim: int | None) -> Episode:
    where = f"{path}: demo '{name}'"
    if "actions" not in group:
        raise DatasetError(f"{where}: missing key 'actions'")
    actions = np.asarray(group["actions"][()], dtype=np.float64)
    if actions.ndim != 2 or actions.shape[0] == 0:
        raise DatasetError(f"{where}: key 'actions' is empty or not 2-D (shape {actions.shape})")
    if action_dim is not None and actions.shape[1] != action_dim:
        raise DatasetError(f"{where}: key 'actions' has width {actions.shape[1]}, expected {action_dim}")
    _check_finite(actions, f"{where}: key 'actions'")
    obs = {}
    for key in obs_keys:
        dataset_path = f"obs/{key}"
        if dataset_path not in group:
            raise DatasetError(f"{where}: missing obs key '{key}'")
        values = np.asarray(group[dataset_path][()], dtype=np.float64)
        if values.shape[0] != actions.shape[0]:
            raise DatasetError(
                f"{where}: obs key '{key}' has {values.shape[0]} steps but 'actions' has {actions.shape[0]}"
            )
        _check_finite(values, f"{where}: obs key '{key}'")
        obs[key] = values.reshape(values.shape[0], -1)
    return Episode(
        obs=obs,
        actions=actions,
        states=group["states"][()] if "states" in group else None,
        rewards=group["rewards"][()] if "rewards" in group else None,
        dones=group["dones"][()] if "dones" in group else None,
        attrs={key: _decode_attr(value) for key, value in group.attrs.items()},
    )


def _check_finite(values: np.ndarray, where: str) -> None:
    if not np.all(np.isfinite(values)):
        step = int(np.argwhere(~np.isfinite(values))[0][0])
        raise DatasetError(f"{where} holds NaN or inf (first at step {step})")
