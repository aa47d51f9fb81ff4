"""Camera frames of a LeRobotDataset's video features (MP4 files), decoded with PyAV for carp's image buffer.

A camera ``c`` of ``data.cameras`` reads the feature ``observation.images.<c>`` (LeRobot's name for camera ``c``) or
``observation.<c>`` (Push-T's single ``observation.image``) and becomes carp's obs key ``<c>_image``. LeRobot v3.0
stores the episodes of a camera one after another in shared MP4 files, an episode starting at its
``videos/<feature>/from_timestamp``; v2.0/v2.1 store one MP4 file per episode, starting at 0 s. Frame ``t`` of an
episode is the decoded frame shown at ``from_timestamp + timestamp[t]``, as LeRobot's own loader picks it (within
its tolerance of 0.1 ms). Frames are resized to ``image_size`` x ``image_size`` (bilinear, the aspect ratio is not
kept) when their size differs, the square images carp's encoders take.
"""

from pathlib import Path

import av
import numpy as np
from PIL import Image

from carp.data.robomimic_schema import IMAGE_KEY_SUFFIX, DatasetError

IMAGE_PREFIX = "observation.images."
OBSERVATION_PREFIX = "observation."
# LeRobot's tolerance between a frame's timestamp and the decoded frame it selects (its ``tolerance_s``).
FRAME_TOLERANCE_S = 1e-4


def camera_feature_names(camera: str) -> tuple[str, ...]:
    """The features a camera may be stored under, in the order they are looked up."""
    return (IMAGE_PREFIX + camera, OBSERVATION_PREFIX + camera)


def image_key(camera: str) -> str:
    """The obs key of a camera's images in carp."""
    return f"{camera}{IMAGE_KEY_SUFFIX}"


def decode_episode(
    video: Path, start_s: float, timestamps: np.ndarray, shape: tuple[int, ...], image_size: int, where: str
) -> np.ndarray:
    """The frames of one episode of one camera.

    Args:
        video: the MP4 file.
        start_s: the episode's first frame time in the file (v3.0's ``from_timestamp``; 0 for v2.x).
        timestamps: (T,) float seconds of the episode's frames, from its first frame.
        shape: the feature's (H, W, 3) per frame in ``info.json``.
        image_size: side of the square images returned.
        where: message prefix naming the episode and the feature.

    Returns:
        (T, image_size, image_size, 3) uint8 RGB frames.

    Raises:
        DatasetError: an unreadable video, a frame size other than ``shape``, or a step without a frame at its time;
            the message names the video, the episode, the feature and the step.
    """
    wanted = start_s + np.asarray(timestamps, dtype=np.float64)
    frames: list[np.ndarray | None] = [None] * len(wanted)
    if not video.is_file():
        raise DatasetError(f"{video}: {where}: file not found (info.json's video_path names it)")
    try:
        with av.open(str(video)) as container:
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            container.seek(max(0, int(wanted[0] / stream.time_base)), stream=stream, backward=True)
            for frame in container.decode(stream):
                time = float(frame.time)
                if time > wanted[-1] + FRAME_TOLERANCE_S:
                    break
                step = int(np.argmin(np.abs(wanted - time)))
                if abs(wanted[step] - time) > FRAME_TOLERANCE_S or frames[step] is not None:
                    continue
                rgb = frame.to_ndarray(format="rgb24")
                if rgb.shape != tuple(shape):
                    raise DatasetError(
                        f"{video}: {where}: step {step}: frame shape={rgb.shape}: info.json's shape is {list(shape)}"
                    )
                frames[step] = _resized(rgb, image_size)
    except (av.error.FFmpegError, IndexError, OSError) as error:
        raise DatasetError(f"{video}: {where}: cannot be decoded ({error})") from None
    missing = [step for step, frame in enumerate(frames) if frame is None]
    if missing:
        step = missing[0]
        raise DatasetError(
            f"{video}: {where}: step {step}: no frame at {wanted[step]:.6g} s ({len(missing)} of {len(wanted)} steps "
            "have none): the video and the frame timestamps disagree"
        )
    return np.stack(frames)


def _resized(rgb: np.ndarray, image_size: int) -> np.ndarray:
    if rgb.shape[:2] == (image_size, image_size):
        return rgb
    return np.asarray(Image.fromarray(rgb).resize((image_size, image_size), Image.BILINEAR), dtype=np.uint8)


# LeRobot's own video settings (its encoder's defaults): AV1 through SVT-AV1, 4:2:0 chroma, a key frame every two
# frames so that any frame decodes quickly, constant quality 30.
VIDEO_CODEC = "libsvtav1"
VIDEO_CODEC_NAME = "av1"
PIXEL_FORMAT = "yuv420p"
VIDEO_OPTIONS = {"g": "2", "crf": "30"}


def encode_video(path: Path, frames: np.ndarray, fps: int) -> None:
    """Write (N, H, W, 3) uint8 RGB frames as an MP4 file, frame n shown at n / fps seconds.

    H and W must be even (4:2:0 chroma halves both). Compression is lossy: decoded frames differ by a few levels.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), mode="w") as container:
        stream = container.add_stream(VIDEO_CODEC, rate=fps, options=VIDEO_OPTIONS)
        stream.pix_fmt = PIXEL_FORMAT
        stream.height, stream.width = int(frames.shape[1]), int(frames.shape[2])
        for rgb in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")))
        container.mux(stream.encode())


def video_info(shape: tuple[int, ...], fps: int) -> dict:
    """The ``info`` entry LeRobot records for a video feature of (H, W, 3) frames."""
    return {
        "video.height": int(shape[0]),
        "video.width": int(shape[1]),
        "video.codec": VIDEO_CODEC_NAME,
        "video.pix_fmt": PIXEL_FORMAT,
        "video.is_depth_map": False,
        "video.fps": int(fps),
        "video.channels": int(shape[2]),
        "has_audio": False,
    }
