"""Disk size of an image replay buffer and the throughput of sampling image windows from it.

Measures either an ingested buffer (`--buffer data/processed/lift/replay.zarr`, ingested with `data.observations:
image`) or, without `--buffer`, a synthetic one written by `carp.data.ingest` from a robomimic-schema file whose
frames are flat-shaded scenes (a shaded background and a moving square, no noise). Synthetic frames compress roughly
as rendered ones do; the numbers to quote come from a real buffer.

Printed: the bytes per demo on disk of each camera's images (compressed, all chunk files) next to their raw size,
then, per number of observation steps `To`, the throughput of reading random batches of windows with
`carp.data.image_windows.ImageWindowReader` (images (B, To, cameras, 3, H, W) uint8, proprioception, actions): the
median over `--batches` batches of the time per batch, and windows/s = batch size / that median. The first batch is
read once before timing (it opens the chunk files' directory). Two ways of reading: `per batch` decodes the chunks
holding each batch's frames (evaluation, and training splits too large for memory); `preloaded` is training's way
when the split fits `carp.training.task_policy.IMAGE_PRELOAD_LIMIT_BYTES`, decoding every frame once when the reader
opens (`open s`) and indexing memory afterwards.

Usage: python benchmarks/image_windows.py [--buffer PATH] [--demos 20] [--steps 60] [--image-size 84]
                                          [--batch-size 64] [--batches 20] [--seed 0]
"""

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import zarr

from carp.data.image_windows import ImageWindowReader
from carp.data.ingest import BUFFER_DIRNAME, ingest_demonstrations
from carp.data.rendering import RenderSettings
from carp.data.robomimic_io import Episode, write_demonstrations
from carp.training.policy_inputs import IMAGE_PRELOAD_LIMIT_BYTES

PROPRIOCEPTION = {"robot0_eef_pos": 3, "robot0_eef_quat": 4, "robot0_gripper_qpos": 2}
HORIZON, ACTION_STEPS = 16, 8


def synthetic_frames(steps: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """(steps, size, size, 3) uint8 frames: a vertical shade and a square that moves across it."""
    rows = np.linspace(60, 200, size, dtype=np.float64)[:, None, None]
    background = np.broadcast_to(rows * rng.uniform(0.6, 1.0, size=3), (size, size, 3))
    frames = np.repeat(background[None], steps, axis=0).astype(np.uint8)
    side = max(1, size // 6)
    path = np.linspace(0, size - side, steps).astype(int)
    colour = rng.integers(0, 256, size=3, dtype=np.uint8)
    for step, corner in enumerate(path):
        frames[step, corner : corner + side, size // 3 : size // 3 + side] = colour
    return frames


def write_synthetic_buffer(folder: Path, demos: int, steps: int, image_size: int, seed: int) -> Path:
    """Ingest a synthetic robomimic image file into ``folder``; returns the replay.zarr path."""
    rng = np.random.default_rng(seed)
    settings = RenderSettings(image_size=image_size)
    episodes = []
    for _ in range(demos):
        obs = {key: rng.normal(size=(steps, width)).cumsum(axis=0) * 0.01 for key, width in PROPRIOCEPTION.items()}
        obs.update({key: synthetic_frames(steps, image_size, rng) for key in settings.image_keys})
        actions = np.concatenate([rng.normal(size=(steps, 3)) * 0.1, np.full((steps, 3), 0.5), np.ones((steps, 1))], 1)
        episodes.append(Episode(obs=obs, actions=actions, states=np.zeros((steps, 1))))
    raw = folder / "synthetic.hdf5"
    write_demonstrations(raw, episodes, {"env_name": "Lift", "type": 1, "env_kwargs": {}})
    ingest_demonstrations(raw, folder / "processed", tuple(PROPRIOCEPTION), camera_settings=settings)
    return folder / "processed" / BUFFER_DIRNAME


def bytes_per_demo(root: Path) -> list[tuple[str, float, float]]:
    """Per image key: (key, compressed bytes per demo on disk, raw bytes per demo)."""
    group = zarr.open_group(str(root), mode="r")
    demos = len(group["meta/episode_ends"])
    rows = []
    for key in group.attrs["image_keys"]:
        on_disk = sum(path.stat().st_size for path in (root / "data" / key).iterdir() if not path.name.startswith("."))
        rows.append((key, on_disk / demos, group[f"data/{key}"].nbytes / demos))
    return rows


def window_throughput(
    root: Path, obs_steps: int, batch_size: int, batches: int, seed: int, preload: bool = False
) -> tuple[float, float]:
    """Seconds to open the reader (decoding every frame when ``preload``) and median seconds per random batch."""
    start = time.perf_counter()
    limit = IMAGE_PRELOAD_LIMIT_BYTES if preload else 0
    reader = ImageWindowReader(root, HORIZON, obs_steps, ACTION_STEPS, preload_limit_bytes=limit)
    opened = time.perf_counter() - start
    rng = np.random.default_rng(seed)
    reader.read(rng.integers(len(reader), size=batch_size))
    seconds = []
    for _ in range(batches):
        indices = rng.integers(len(reader), size=batch_size)
        start = time.perf_counter()
        reader.read(indices)
        seconds.append(time.perf_counter() - start)
    return opened, statistics.median(seconds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--buffer", type=Path, help="an ingested image replay.zarr (default: a synthetic one)")
    parser.add_argument("--demos", type=int, default=20)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--image-size", type=int, default=84)
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--batches", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    for name in ("demos", "steps", "image_size", "batch_size", "batches"):
        if getattr(args, name) < 1:
            print(f"error: --{name.replace('_', '-')}={getattr(args, name)}: must be >= 1", file=sys.stderr)
            sys.exit(1)
    if args.buffer is not None and not (args.buffer / ".zgroup").is_file():
        print(f"error: --buffer={args.buffer}: not a zarr replay buffer", file=sys.stderr)
        sys.exit(1)

    with tempfile.TemporaryDirectory() as folder:
        root = args.buffer or write_synthetic_buffer(Path(folder), args.demos, args.steps, args.image_size, args.seed)
        group = zarr.open_group(str(root), mode="r")
        if "image_keys" not in group.attrs:
            print(f"error: --buffer={root}: holds no images (ingest with data.observations: image)", file=sys.stderr)
            sys.exit(1)
        first = group[f"data/{group.attrs['image_keys'][0]}"]
        source = "synthetic" if args.buffer is None else str(root)
        print(
            f"{source}: {len(group['meta/episode_ends'])} demos, {first.shape[0]} frames of "
            f"{first.shape[1]}x{first.shape[2]}, chunks of {first.chunks[0]} frames, {first.compressor}"
        )
        print(f"{'image key':<28}{'bytes/demo on disk':>20}{'bytes/demo raw':>16}{'ratio':>8}")
        total = 0.0
        for key, on_disk, raw in bytes_per_demo(root):
            total += on_disk
            print(f"{key:<28}{on_disk:>20.0f}{raw:>16.0f}{raw / on_disk:>8.2f}")
        print(f"{'all cameras':<28}{total:>20.0f}")
        print(f"{'reads':<12}{'To':>4}{'batch':>8}{'open s':>9}{'ms/batch':>12}{'windows/s':>12}")
        for preload in (False, True):
            for obs_steps in (1, 2):
                opened, seconds = window_throughput(root, obs_steps, args.batch_size, args.batches, args.seed, preload)
                print(
                    f"{'preloaded' if preload else 'per batch':<12}{obs_steps:>4}{args.batch_size:>8}{opened:>9.2f}"
                    f"{seconds * 1e3:>12.3f}{args.batch_size / seconds:>12.0f}"
                )


if __name__ == "__main__":
    main()
