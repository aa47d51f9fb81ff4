"""Checks of the robomimic schema (layout in :mod:`carp.data.robomimic_io`), each failure one :class:`DatasetError`.

Order of the checks, so that a bad file fails on its first problem with a message naming the file, demo and key,
never inside numpy or h5py:

1. the file opens (missing, not HDF5, truncated, locked by a writer and damaged files each get their own line);
2. every dataset a demo must have is a dataset (not a group), holds numbers (not strings or objects) and has the
   schema's shape (T steps in every key, the expected action width, the same obs widths in every demo; camera images,
   the obs keys ending in ``_image``, are uint8 (T, H, W, 3) of one size in every demo), all checked from the file's
   metadata before any value is read;
3. low-dimensional values are finite in float32, the dtype the replay buffer stores (1e39 is finite in float64 but
   ``inf`` in the buffer), and every column's range across the demos, squared, is finite in float32 (normalization
   divides by the range; errors in original units are squared multiples of it);
4. every ``mask/<name>`` list names existing demos, whichever of them ``filter_key`` selects, and ``mask/valid``
   leaves at least one of the selected demos to train on.

Any OSError or h5py error raised while a check reads the file becomes a :class:`DatasetError` naming where it happened.
"""

import math
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

# The replay buffer's dtype (carp.data.replay_buffer); values must be finite in it, not only in float64.
STORED_DTYPE = np.float32
# Per-demo datasets that are read when present but not used by ingestion (only their kind and steps are checked).
OPTIONAL_KEYS = ("states", "rewards", "dones")
# robomimic's RGB observations: obs keys ending in "_image", uint8 (T, H, W, 3) upright RGB images. They are stored
# as they are (never converted to float), so the finiteness and range checks do not apply to them.
IMAGE_KEY_SUFFIX = "_image"
IMAGE_DTYPE = np.uint8
IMAGE_CHANNELS = 3


def is_image_key(key: str) -> bool:
    """Whether an obs key holds camera images (robomimic's ``<camera>_image``)."""
    return key.endswith(IMAGE_KEY_SUFFIX)


class DatasetError(ValueError):
    """A demonstration file that does not follow the schema or holds unusable values."""


@dataclass(frozen=True)
class DemoLayout:
    """Shapes of one demo, read from the file's metadata.

    Attributes:
        steps: T, the number of actions.
        obs_widths: obs key -> features per step (the product of the dataset's trailing dimensions).
        obs_shapes: obs key -> the dataset's shape per step, e.g. (H, W, 3) for images.
    """

    steps: int
    obs_widths: dict[str, int]
    obs_shapes: dict[str, tuple[int, ...]]


@contextmanager
def hdf5_errors(where: str) -> Iterator[None]:
    """Turn an OSError or h5py error raised inside the block into one :class:`DatasetError` line naming ``where``."""
    try:
        yield
    except (OSError, KeyError, RuntimeError, TypeError) as error:
        raise DatasetError(f"{where}: {_explain(error)}") from None


def _explain(error: BaseException) -> str:
    # str() of a KeyError quotes its message; OSErrors carry the errno first in args, the text only in str().
    text = str(error.args[0] if isinstance(error, KeyError) and error.args else error).strip()
    text = text.splitlines()[0] if text else type(error).__name__
    if "unable to lock file" in text:
        return "another process holds the file open for writing (HDF5 file lock); run again once it has finished"
    if "truncated file" in text:
        detail = text[text.index("truncated file") :].rstrip(")")
        return f"the file is truncated ({detail}): it was not completely written or copied"
    return f"cannot read ({text}): the file is damaged or unreadable"


def open_hdf5(path: Path) -> h5py.File:
    """Open ``path`` read-only.

    Raises:
        DatasetError: missing, not a file, not HDF5, truncated, held open by a writer, or unreadable.
    """
    if not path.exists():
        raise DatasetError(f"{path}: file not found")
    if not path.is_file():
        raise DatasetError(f"{path}: not a file")
    with hdf5_errors(str(path)):
        if not h5py.is_hdf5(path):
            raise DatasetError(f"{path}: not an HDF5 file")
        return h5py.File(path, "r")


def require_group(parent: h5py.Group, key: str, label: str) -> h5py.Group:
    """``parent[key]`` if it is a group; ``label`` names it in the message ("<file>: demo 'demo_0': group 'obs'")."""
    node = _require_node(parent, key, label)
    if not isinstance(node, h5py.Group):
        raise DatasetError(f"{label}: is a {_kind(node)}, expected a group")
    return node


def require_numeric_dataset(parent: h5py.Group, key: str, label: str) -> h5py.Dataset:
    """``parent[key]`` if it is a dataset of numbers with a shape (checked from metadata, no values read)."""
    dataset = _require_dataset(parent, key, label)
    with hdf5_errors(label):
        dtype = dataset.dtype
    if dtype.kind not in "fiu":
        raise DatasetError(f"{label}: dtype={_describe_dtype(dtype)}: expected numbers (float or integer)")
    if dataset.shape is None:
        raise DatasetError(f"{label}: shape=None: the dataset is empty (no dataspace)")
    return dataset


def _require_dataset(parent: h5py.Group, key: str, label: str) -> h5py.Dataset:
    node = _require_node(parent, key, label)
    if not isinstance(node, h5py.Dataset):
        raise DatasetError(f"{label}: is a {_kind(node)}, expected a dataset")
    return node


def _require_node(parent: h5py.Group, key: str, label: str):
    with hdf5_errors(label):
        if key not in parent:
            raise DatasetError(f"{label}: missing")
        return parent[key]


def _kind(node) -> str:
    return {h5py.Group: "group", h5py.Dataset: "dataset", h5py.Datatype: "named datatype"}.get(type(node), "link")


def _describe_dtype(dtype: np.dtype) -> str:
    if h5py.check_string_dtype(dtype) is not None or dtype.kind in "SU":
        return f"{dtype} (strings)"
    return str(dtype)


def check_demo_layout(group: h5py.Group, where: str, obs_keys: Sequence[str], action_dim: int | None) -> DemoLayout:
    """Check one demo's datasets against the schema from metadata alone.

    Args:
        group: ``data/demo_<i>``.
        where: message prefix naming the file and demo.
        obs_keys: obs keys that must be present.
        action_dim: expected action width; ``None`` accepts any.

    Raises:
        DatasetError: a missing key, a group where a dataset belongs, a non-numeric dtype, a wrong shape, or an image
            key that is not uint8 (T, H, W, 3).
    """
    label = f"{where}: key 'actions'"
    shape = require_numeric_dataset(group, "actions", label).shape
    expected = f"(T, {action_dim if action_dim is not None else 'A'})"
    if len(shape) != 2:
        raise DatasetError(f"{label}: shape={shape}: expected {expected}")
    if 0 in shape:
        raise DatasetError(f"{label}: shape={shape}: the dataset is empty")
    if action_dim is not None and shape[1] != action_dim:
        raise DatasetError(f"{label}: shape={shape}: expected width {action_dim}, i.e. {expected}")
    steps = shape[0]
    obs = require_group(group, "obs", f"{where}: group 'obs'")
    widths, shapes = {}, {}
    for key in obs_keys:
        label = f"{where}: obs key '{key}'"
        dataset = require_numeric_dataset(obs, key, label)
        shape = dataset.shape
        if is_image_key(key):
            _require_images(dataset, label)
        _require_steps(shape, steps, label)
        widths[key], shapes[key] = math.prod(shape[1:]), tuple(shape[1:])
        if widths[key] == 0:
            raise DatasetError(f"{label}: shape={shape}: the dataset is empty")
    for key in OPTIONAL_KEYS:
        with hdf5_errors(where):
            present = key in group
        if present:
            label = f"{where}: key '{key}'"
            _require_steps(require_numeric_dataset(group, key, label).shape, steps, label)
    return DemoLayout(steps=steps, obs_widths=widths, obs_shapes=shapes)


def _require_images(dataset: h5py.Dataset, label: str) -> None:
    with hdf5_errors(label):
        dtype, shape = dataset.dtype, dataset.shape
    if dtype != IMAGE_DTYPE or len(shape) != 4 or shape[-1] != IMAGE_CHANNELS:
        raise DatasetError(
            f"{label}: shape={shape}, dtype={dtype}: expected {np.dtype(IMAGE_DTYPE).name} RGB images "
            f"(T, H, W, {IMAGE_CHANNELS}) as robomimic stores them"
        )


def _require_steps(shape: tuple[int, ...], steps: int, label: str) -> None:
    if len(shape) == 0:
        raise DatasetError(f"{label}: shape=(): expected ({steps}, ...), one row per step")
    if shape[0] != steps:
        raise DatasetError(f"{label}: shape={shape}: has {shape[0]} steps but 'actions' has {steps}")


def check_same_widths(path: Path, names: Sequence[str], layouts: Sequence[DemoLayout]) -> None:
    """Every demo's obs keys must have the first demo's widths, and images its size (ingestion stacks all demos).

    Raises:
        DatasetError: names both demos, the key and both widths (both shapes for images).
    """
    first_name, first = names[0], layouts[0]
    for name, layout in zip(names[1:], layouts[1:]):
        for key, width in layout.obs_widths.items():
            if is_image_key(key) and layout.obs_shapes[key] != first.obs_shapes[key]:
                raise DatasetError(
                    f"{path}: demo '{name}': obs key '{key}': shape=({layout.steps}, "
                    f"{', '.join(map(str, layout.obs_shapes[key]))}): image size differs from demo '{first_name}' "
                    f"(T, {', '.join(map(str, first.obs_shapes[key]))}); every demo must have the same image size"
                )
            if width != first.obs_widths[key]:
                raise DatasetError(
                    f"{path}: demo '{name}': obs key '{key}': width={width}: differs from demo '{first_name}' "
                    f"(width {first.obs_widths[key]}); every demo must have the same obs widths"
                )


def read_images(dataset: h5py.Dataset, label: str) -> np.ndarray:
    """A checked image dataset's values, (T, H, W, 3) uint8 as stored."""
    with hdf5_errors(label):
        return np.asarray(dataset[()], dtype=IMAGE_DTYPE)


def read_values(dataset: h5py.Dataset, label: str) -> np.ndarray:
    """A checked dataset's values as float64, refused unless every one is finite in :data:`STORED_DTYPE`."""
    with hdf5_errors(label):
        values = np.asarray(dataset[()], dtype=np.float64)
    check_stored_dtype(values, label)
    return values


def check_stored_dtype(values: np.ndarray, label: str) -> None:
    """Refuse NaN, inf and values that overflow :data:`STORED_DTYPE` in (T, ...) ``values``.

    Raises:
        DatasetError: names the step, column and value of the first one.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        finite = np.isfinite(values.astype(STORED_DTYPE))
    if not finite.all():
        index = tuple(int(i) for i in np.argwhere(~finite)[0])
        raise DatasetError(
            f"{label}: {_position(index)}: value={float(values[index])!r}: not a finite "
            f"{np.dtype(STORED_DTYPE).name} number (the replay buffer stores {np.dtype(STORED_DTYPE).name})"
        )


def check_stored_ranges(path: Path, names: Sequence[str], key: str, arrays: Sequence[np.ndarray]) -> None:
    """Every column's range over all demos, and its square, must be finite in :data:`STORED_DTYPE`.

    Normalization divides by the range, and errors in original units (the tokenizer's held-out RMSE) are squared
    multiples of it, so a column spanning more than about 1.8e19 (the square root of float32's largest number) cannot
    be measured even though each of its values fits.

    Args:
        path: the file (for the message).
        names: demo names, one per array.
        key: label of the key, e.g. ``key 'actions'`` or ``obs key 'object'``.
        arrays: (T_i, F) values of that key in each demo, already checked by :func:`check_stored_dtype`.

    Raises:
        DatasetError: names the demo, step, column and value of the column's largest magnitude.
    """
    stored = [array.reshape(array.shape[0], -1).astype(STORED_DTYPE) for array in arrays]
    lows = np.min([values.min(axis=0) for values in stored], axis=0)
    highs = np.max([values.max(axis=0) for values in stored], axis=0)
    with np.errstate(over="ignore"):
        spans = highs - lows
        too_wide = ~np.isfinite(spans * spans)
    if not too_wide.any():
        return
    column = int(np.flatnonzero(too_wide)[0])
    magnitudes = [np.abs(values[:, column]) for values in stored]
    demo = int(np.argmax([magnitude.max() for magnitude in magnitudes]))
    step = int(np.argmax(magnitudes[demo]))
    value = float(arrays[demo].reshape(arrays[demo].shape[0], -1)[step, column])
    raise DatasetError(
        f"{path}: demo '{names[demo]}': {key}: step {step}, column {column}: value={value!r}: the column spans "
        f"{float(lows[column]):g} to {float(highs[column]):g} over the demos, too wide for "
        f"{np.dtype(STORED_DTYPE).name}: normalization divides by the range and squared errors overflow"
    )


def _position(index: tuple[int, ...]) -> str:
    if len(index) == 1:
        return f"step {index[0]}"
    if len(index) == 2:
        return f"step {index[0]}, column {index[1]}"
    return f"step {index[0]}, element {index[1:]}"


def read_masks(handle: h5py.File, path: Path, demo_names: Sequence[str]) -> dict[str, list[str]]:
    """Every ``mask/<name>`` list of the file, each checked to name existing demos, once each.

    Raises:
        DatasetError: a mask that is not a 1-D list of names, or names a missing or repeated demo.
    """
    with hdf5_errors(str(path)):
        present = "mask" in handle
    if not present:
        return {}
    group = require_group(handle, "mask", f"{path}: group 'mask'")
    with hdf5_errors(f"{path}: group 'mask'"):
        keys = list(group.keys())
    return {key: _read_mask(group, key, f"{path}: mask 'mask/{key}'", set(demo_names)) for key in keys}


def _read_mask(group: h5py.Group, key: str, label: str, demo_names: set[str]) -> list[str]:
    dataset = _require_dataset(group, key, label)
    with hdf5_errors(label):
        dtype, shape = dataset.dtype, dataset.shape
    if h5py.check_string_dtype(dtype) is None and dtype.kind not in "SU":
        raise DatasetError(f"{label}: dtype={dtype}: expected demo names (strings)")
    if shape is None or len(shape) != 1:
        raise DatasetError(f"{label}: shape={shape}: expected a list of demo names")
    with hdf5_errors(label):
        entries = list(dataset[()])
    names = []
    for entry in entries:
        try:
            name = entry.decode() if isinstance(entry, bytes) else str(entry)
        except UnicodeDecodeError:
            raise DatasetError(f"{label}: entry {entry!r}: not UTF-8 text") from None
        if name not in demo_names:
            raise DatasetError(f"{label}: names demo '{name}', which does not exist")
        if name in names:
            raise DatasetError(f"{label}: names demo '{name}' twice")
        names.append(name)
    return names


def check_valid_mask(path: Path, names: Sequence[str], masks: dict[str, list[str]], filter_key: str | None) -> None:
    """Refuse a ``mask/valid`` that lists every demo read: no demo would be left to train on.

    ``mask/valid`` holds demos out of training. When it lists every one of ``names`` (the demos ``filter_key``
    selects), no split is possible. A ``filter_key`` of ``valid`` asks to train on the listed demos themselves, so
    there the mask is the selection (and ingestion holds out its last ``valid_fraction``).

    Raises:
        DatasetError: names the file, the mask and the count of demos.
    """
    listed = set(masks.get("valid", []))
    if filter_key == "valid" or not listed or not names or not set(names) <= listed:
        return
    selection = f"selected by 'mask/{filter_key}'" if filter_key is not None else "in the file"
    raise DatasetError(
        f"{path}: mask 'mask/valid': lists all {len(names)} demos {selection}, leaving none to train on; list "
        "only the held-out demos there, or remove it to hold out the last data.valid_fraction"
    )
