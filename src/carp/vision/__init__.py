"""Image observations shared by every policy family: the camera encoder, its crops and its config.

The encoder lives outside ``carp.policies`` because it is not a family: every family (CARP and the baselines) plugs
the same :class:`ImageEncoder` in front of its own model, configured once by :class:`ImageEncoderConfig` (a params
section, defined in :mod:`carp.config`). Rendering the images from simulator states is data preparation and lives
in :mod:`carp.data.rendering`.
"""

from carp.config.image_encoder import ImageEncoderConfig
from carp.vision.encoder import CameraEncoder, ImageEncoder

__all__ = ["CameraEncoder", "ImageEncoder", "ImageEncoderConfig"]
