"""Corrupt robomimic files: each case damages a valid synthetic file one way and says what the error must name.

Used by the unit tests of the checks (`tests/data/test_robomimic_schema.py`, `tests/data/test_ingest.py`) and by the
stage-level suite (`tests/reliability/test_corrupt_data_stages.py`), so every damage is exercised at both levels.
The valid file is `tests.conftest.write_synthetic_file`: demos demo_0..demo_3 of 30, 25, 40 and 20 steps, obs keys
`OBS_KEYS`, 7-D actions, `mask/train` = demo_0..demo_2 and `mask/valid` = demo_3. The cases on camera images damage
the same file written with `IMAGE_SIZE` x `IMAGE_SIZE` images under `IMAGE_KEYS`, read with those keys too.
"""

import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from tests.conftest import IMAGE_KEYS, OBS_KEYS, write_synthetic_file

IMAGE_SIZE = 8


@dataclass(frozen=True)
class CorruptCase:
    """One way to damage the valid file.

    Attributes:
        damage: edits the written file in place (``None``: left valid, e.g. when a writer holds it open).
        location: the demo and key the message must name, as it follows the file's path ("" for the whole file).
        problem: what the message must say after the location.
        hold_open: a writer process keeps the file open for writing while it is read.
        with_images: the valid file has camera images, and they are read (:attr:`obs_keys`).
    """

    damage: Callable[[Path], None] | None
    location: str
    problem: str
    hold_open: bool = False
    with_images: bool = False

    @property
    def obs_keys(self) -> tuple[str, ...]:
        """The obs keys the file is read with."""
        return (*OBS_KEYS, *IMAGE_KEYS) if self.with_images else OBS_KEYS


def _edit(change: Callable[[h5py.File], None]) -> Callable[[Path], None]:
    def damage(path: Path) -> None:
        with h5py.File(path, "r+") as handle:
            change(handle)

    return damage


def _replace(key: str, values) -> Callable[[Path], None]:
    def change(handle: h5py.File) -> None:
        del handle[key]
        if isinstance(values, str):
            handle.create_group(key)
        else:
            handle.create_dataset(key, data=values)

    return _edit(change)


def _set(key: str, index: tuple[int, ...], value: float) -> Callable[[Path], None]:
    return _edit(lambda handle: handle[key].__setitem__(index, value))


def _set_many(*edits: tuple[str, tuple[int, ...], float]) -> Callable[[Path], None]:
    def change(handle: h5py.File) -> None:
        for key, index, value in edits:
            handle[key][index] = value

    return _edit(change)


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(0.6 * len(data))])


def _damage_object_header(key: str) -> Callable[[Path], None]:
    """Overwrite the first bytes of ``key``'s object header, as a bad sector or a torn write would."""

    def damage(path: Path) -> None:
        with h5py.File(path, "r") as handle:
            address = h5py.h5o.get_info(handle[key].id).addr
        with open(path, "r+b") as stream:
            stream.seek(address)
            stream.write(b"\xff" * 16)

    return damage


def _not_hdf5(path: Path) -> None:
    path.write_text("demo_0,demo_1\n")


STRINGS = np.full((25, 7), b"0.5", dtype="S3")

CORRUPT_FILES: dict[str, CorruptCase] = {
    "truncated": CorruptCase(_truncate, "", "the file is truncated"),
    "held open for writing": CorruptCase(None, "", "another process holds the file open for writing", True),
    "not hdf5": CorruptCase(_not_hdf5, "", "not an HDF5 file"),
    "damaged object header": CorruptCase(
        _damage_object_header("data/demo_1/actions"), "demo 'demo_1': key 'actions'", "the file is damaged"
    ),
    "actions as strings": CorruptCase(
        _replace("data/demo_1/actions", STRINGS), "demo 'demo_1': key 'actions'", "dtype=|S3 (strings): expected"
    ),
    "actions as variable-length strings": CorruptCase(
        _edit(
            lambda h: (
                h.__delitem__("data/demo_1/actions"),
                h.create_dataset("data/demo_1/actions", data=STRINGS.astype(object), dtype=h5py.string_dtype()),
            )
        ),
        "demo 'demo_1': key 'actions'",
        "dtype=object (strings): expected numbers",
    ),
    "obs key is a group": CorruptCase(
        _replace("data/demo_2/obs/object", "group"), "demo 'demo_2': obs key 'object'", "is a group, expected a dataset"
    ),
    "actions is a group": CorruptCase(
        _replace("data/demo_0/actions", "group"), "demo 'demo_0': key 'actions'", "is a group, expected a dataset"
    ),
    "obs widths differ between demos": CorruptCase(
        _replace("data/demo_2/obs/object", np.zeros((40, 9))),
        "demo 'demo_2': obs key 'object'",
        "width=9: differs from demo 'demo_0' (width 10)",
    ),
    "action overflows float32": CorruptCase(
        _set("data/demo_3/actions", (4, 2), 1e39),
        "demo 'demo_3': key 'actions'",
        "step 4, column 2: value=1e+39: not a finite float32 number",
    ),
    "obs overflows float32": CorruptCase(
        _set("data/demo_0/obs/robot0_eef_pos", (7, 1), -1e39),
        "demo 'demo_0': obs key 'robot0_eef_pos'",
        "step 7, column 1: value=-1e+39: not a finite float32 number",
    ),
    "action 1e30 makes squared errors overflow": CorruptCase(
        _set("data/demo_1/actions", (3, 0), 1e30),
        "demo 'demo_1': key 'actions'",
        "step 3, column 0: value=1e+30: the column spans",
    ),
    "obs range overflows float32": CorruptCase(
        _set_many(("data/demo_0/obs/object", (2, 4), -3e38), ("data/demo_2/obs/object", (5, 4), 3.2e38)),
        "demo 'demo_2': obs key 'object'",
        "step 5, column 4: value=3.2e+38: the column spans -3e+38 to 3.2e+38",
    ),
    "nan action": CorruptCase(
        _set("data/demo_3/actions", (4, 2), np.nan), "demo 'demo_3': key 'actions'", "step 4, column 2: value=nan"
    ),
    "inf obs": CorruptCase(
        _set("data/demo_0/obs/robot0_eef_quat", (7, 0), np.inf),
        "demo 'demo_0': obs key 'robot0_eef_quat'",
        "step 7, column 0: value=inf",
    ),
    "missing data group": CorruptCase(_edit(lambda h: h.move("data", "stuff")), "group 'data'", "missing"),
    "missing actions": CorruptCase(
        _edit(lambda h: h.__delitem__("data/demo_2/actions")), "demo 'demo_2': key 'actions'", "missing"
    ),
    "missing obs group": CorruptCase(
        _edit(lambda h: h.__delitem__("data/demo_1/obs")), "demo 'demo_1': group 'obs'", "missing"
    ),
    "missing obs key": CorruptCase(
        _edit(lambda h: h.__delitem__("data/demo_1/obs/object")), "demo 'demo_1': obs key 'object'", "missing"
    ),
    "empty actions": CorruptCase(
        _replace("data/demo_0/actions", np.zeros((0, 7))),
        "demo 'demo_0': key 'actions'",
        "shape=(0, 7): the dataset is empty",
    ),
    "actions without a dataspace": CorruptCase(
        _replace("data/demo_0/actions", h5py.Empty("f8")),
        "demo 'demo_0': key 'actions'",
        "shape=None: the dataset is empty",
    ),
    "obs of width 0": CorruptCase(
        _replace("data/demo_3/obs/robot0_gripper_qpos", np.zeros((20, 0))),
        "demo 'demo_3': obs key 'robot0_gripper_qpos'",
        "shape=(20, 0): the dataset is empty",
    ),
    "actions not 2-D": CorruptCase(
        _replace("data/demo_1/actions", np.zeros(25)), "demo 'demo_1': key 'actions'", "shape=(25,): expected (T, 7)"
    ),
    "wrong action width": CorruptCase(
        _replace("data/demo_1/actions", np.zeros((25, 6))),
        "demo 'demo_1': key 'actions'",
        "shape=(25, 6): expected width 7",
    ),
    "obs steps differ from actions": CorruptCase(
        _replace("data/demo_2/obs/robot0_eef_pos", np.zeros((39, 3))),
        "demo 'demo_2': obs key 'robot0_eef_pos'",
        "shape=(39, 3): has 39 steps but 'actions' has 40",
    ),
    "mask names a missing demo": CorruptCase(
        _replace("mask/train", np.array([b"demo_0", b"demo_9"])),
        "mask 'mask/train'",
        "names demo 'demo_9', which does not exist",
    ),
    "mask repeats a demo": CorruptCase(
        _replace("mask/valid", np.array([b"demo_3", b"demo_3"])), "mask 'mask/valid'", "names demo 'demo_3' twice"
    ),
    "mask of numbers": CorruptCase(
        _replace("mask/valid", np.array([3])), "mask 'mask/valid'", "expected demo names (strings)"
    ),
    "image of floats": CorruptCase(
        _replace("data/demo_1/obs/agentview_image", np.zeros((25, IMAGE_SIZE, IMAGE_SIZE, 3), dtype=np.float32)),
        "demo 'demo_1': obs key 'agentview_image'",
        "shape=(25, 8, 8, 3), dtype=float32: expected uint8 RGB images (T, H, W, 3)",
        with_images=True,
    ),
    "grey image without a channel axis": CorruptCase(
        _replace("data/demo_2/obs/robot0_eye_in_hand_image", np.zeros((40, IMAGE_SIZE, IMAGE_SIZE), dtype=np.uint8)),
        "demo 'demo_2': obs key 'robot0_eye_in_hand_image'",
        "shape=(40, 8, 8), dtype=uint8: expected uint8 RGB images (T, H, W, 3)",
        with_images=True,
    ),
    "RGBA image": CorruptCase(
        _replace("data/demo_0/obs/agentview_image", np.zeros((30, IMAGE_SIZE, IMAGE_SIZE, 4), dtype=np.uint8)),
        "demo 'demo_0': obs key 'agentview_image'",
        "shape=(30, 8, 8, 4), dtype=uint8: expected uint8 RGB images (T, H, W, 3)",
        with_images=True,
    ),
    "image steps differ from actions": CorruptCase(
        _replace("data/demo_3/obs/agentview_image", np.zeros((19, IMAGE_SIZE, IMAGE_SIZE, 3), dtype=np.uint8)),
        "demo 'demo_3': obs key 'agentview_image'",
        "shape=(19, 8, 8, 3): has 19 steps but 'actions' has 20",
        with_images=True,
    ),
    "image sizes differ between demos": CorruptCase(
        _replace("data/demo_2/obs/robot0_eye_in_hand_image", np.zeros((40, 6, 6, 3), dtype=np.uint8)),
        "demo 'demo_2': obs key 'robot0_eye_in_hand_image'",
        "shape=(40, 6, 6, 3): image size differs from demo 'demo_0' (T, 8, 8, 3)",
        with_images=True,
    ),
    "env_args not JSON": CorruptCase(
        _edit(lambda h: h["data"].attrs.__setitem__("env_args", "{'env_name': Lift")),
        "data.attrs['env_args']",
        "not JSON",
    ),
}

# Writes part of a file and keeps it open until its stdin closes: a download or a collection still in progress.
_WRITER = """
import sys
import h5py
import numpy as np

with h5py.File(sys.argv[1], "w") as handle:
    handle.create_dataset("data/demo_0/actions", data=np.zeros((30, 7)))
    handle.flush()
    print("ready", flush=True)
    sys.stdin.read()
"""


@contextmanager
def corrupt_file(name: str, path: Path) -> Iterator[CorruptCase]:
    """Write the valid file at ``path``, damage it as case ``name`` says, and keep it so while the block runs."""
    case = CORRUPT_FILES[name]
    path.parent.mkdir(parents=True, exist_ok=True)
    if not case.hold_open:
        write_synthetic_file(path, image_size=IMAGE_SIZE if case.with_images else None)
        case.damage(path)
        yield case
        return
    writer = subprocess.Popen(
        [sys.executable, "-c", _WRITER, str(path)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert writer.stdout.readline().strip() == "ready"
        yield case
    finally:
        writer.stdin.close()
        writer.wait(timeout=60)


def expected_message(case: CorruptCase, path: Path) -> str:
    """The start of the error's text: the file, then the location when the case names one."""
    return f"{path}: {case.location}" if case.location else f"{path}: "
