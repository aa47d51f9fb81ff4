"""The `image_encoder` section: the camera encoder every family puts in front of its network."""

from dataclasses import dataclass, replace
from typing import ClassVar

from carp.config.checks import _is_int, _require

# GroupNorm as in Diffusion Policy: one group per 16 channels, so every stage width must be a multiple of 16.
CHANNELS_PER_GROUP = 16
STANDARD_BASE_CHANNELS = 64
LIGHT_BASE_CHANNELS = 16


@dataclass(frozen=True)
class ImageEncoderConfig:
    """Cameras, crop and network sizes of the image encoder (:class:`carp.vision.encoder.ImageEncoder`).

    Defaults are Diffusion Policy's image recipe (robomimic's ``VisualCore``): per camera a ResNet-18 trunk trained
    from scratch with GroupNorm, a spatial-softmax head of 32 keypoints projected to 64 features, and crops of
    76 x 76 pixels from 84 x 84 images; :meth:`light` is the CPU-sized variant. In ``params.yaml`` the
    ``image_encoder`` section holds the network's settings; its cameras and image size are ``data.cameras`` and
    ``data.image_size`` (the images ingest stored).

    Attributes:
        cameras: robosuite camera names, one encoder each; their images are the obs keys ``<camera>_image``;
            at least one, no repeats. In ``params.yaml`` it is ``data.cameras``: leave it out of this section.
        image_size: height and width of the stored images in pixels (robomimic: 84); an integer >= 1. In
            ``params.yaml`` it is ``data.image_size``: leave it out of this section.
        crop_size: side of the square crop fed to the network, random in training and centred in evaluation
            (Diffusion Policy: 76); an integer in [1, image_size].
        base_channels: channels of the ResNet-18 stem; the four stages have 1, 2, 4 and 8 times as many. 64 is the
            standard ResNet-18 (11.2 M trunk parameters per camera), 16 the light CPU variant (0.70 M); a positive
            multiple of 16 (GroupNorm uses one group per 16 channels).
        num_keypoints: K, spatial-softmax keypoints per camera (Diffusion Policy: 32); an integer >= 1.
        feature_dim: features per camera after projecting the 2K keypoint coordinates (Diffusion Policy: 64); an
            integer >= 1.
    """

    SECTION: ClassVar[str] = "image_encoder"

    cameras: tuple[str, ...] = ("agentview", "robot0_eye_in_hand")
    image_size: int = 84
    crop_size: int = 76
    base_channels: int = STANDARD_BASE_CHANNELS
    num_keypoints: int = 32
    feature_dim: int = 64

    def __post_init__(self) -> None:
        section = self.SECTION
        object.__setattr__(self, "cameras", tuple(self.cameras))
        _require(len(self.cameras) > 0, f"{section}.cameras", list(self.cameras), "must name at least one camera")
        _require(
            all(isinstance(camera, str) and camera for camera in self.cameras),
            f"{section}.cameras",
            list(self.cameras),
            "must be non-empty camera names",
        )
        _require(
            len(set(self.cameras)) == len(self.cameras),
            f"{section}.cameras",
            list(self.cameras),
            "names a camera twice",
        )
        for name in ("image_size", "num_keypoints", "feature_dim"):
            value = getattr(self, name)
            _require(_is_int(value) and value >= 1, f"{section}.{name}", value, "must be an integer >= 1")
        _require(
            _is_int(self.crop_size) and 1 <= self.crop_size <= self.image_size,
            f"{section}.crop_size",
            self.crop_size,
            f"must be an integer in [1, image_size={self.image_size}]",
        )
        _require(
            _is_int(self.base_channels) and self.base_channels >= 1 and self.base_channels % CHANNELS_PER_GROUP == 0,
            f"{section}.base_channels",
            self.base_channels,
            f"must be a positive multiple of {CHANNELS_PER_GROUP} (GroupNorm has one group per {CHANNELS_PER_GROUP} "
            "channels)",
        )

    @property
    def image_keys(self) -> tuple[str, ...]:
        """Obs keys of the cameras' images in the robomimic schema, in camera order."""
        return tuple(f"{camera}_image" for camera in self.cameras)

    def light(self) -> "ImageEncoderConfig":
        """This config with the CPU-sized trunk (``base_channels`` 16: 0.70 M parameters per camera, not 11.2 M)."""
        return replace(self, base_channels=LIGHT_BASE_CHANNELS)
