"""The serving protocol a checkpoint records about itself, so that `carp serve` needs nothing but the file.

Training writes the record (a leaf module: it imports nothing of carp's, so the training stage does not reach the
server); `carp.serving.startup.spec_from_protocol` reads it back into the server's spec.

Training stores, under the checkpoint metadata's `SERVING_METADATA_KEY`, what a robot must send and how it must
execute the replies: the low-dim observation keys in order with each key's width (the replay buffer's `obs_keys` and
`obs_widths`, which ingestion read from the demo file), `To`, `H`, `Ta`, the observation kind and, for an image
policy, its cameras and image size. Inference settings are not part of it: they are evaluation params (changing them
must not retrain), so the server takes them from `--params` or the family's defaults.

The stored value is a map of plain values::

    {"format": 1, "observations": "state" | "image", "obs_keys": [...], "obs_widths": [...],
     "obs_steps": To, "action_horizon": H, "action_steps": Ta, "cameras": [...], "image_size": int | None}
"""

from collections.abc import Mapping
from typing import Any

SERVING_METADATA_KEY = "serving"
PROTOCOL_FORMAT = 1
"""Version of the stored map; a reader refuses others."""


class ProtocolError(ValueError):
    """A checkpoint's recorded protocol is missing, of another format or inconsistent with its policy."""


def training_protocol(
    data, buffer_attrs: Mapping[str, Any], image_encoder=None, control_frequency_hz: int | None = None
) -> dict[str, Any]:
    """The protocol of a policy trained with `data` on the replay buffer whose attributes are `buffer_attrs`.

    Args:
        data: the params' data section (`carp.config.DataConfig`): `To`, `H` and `Ta`.
        buffer_attrs: the replay buffer's attributes (`carp.data.replay_buffer`): ``obs_keys`` and ``obs_widths``,
            the low-dim keys concatenated into the policy's `Do` features and each key's width.
        image_encoder: the camera encoder of an image policy (`carp.config.ImageEncoderConfig`: its cameras and
            image size are the images the policy sees); None for a state policy.
        control_frequency_hz: control steps per second of the task the buffer holds, recorded so that a server
            needs no task registry to pace a robot (a task without a simulator is known only from its dataset);
            None leaves it to the server's task registry.

    Raises:
        ProtocolError: the attributes lack the keys or widths (a buffer ingested before they were recorded); the
            message names the missing attribute.
    """
    missing = [key for key in ("obs_keys", "obs_widths") if key not in buffer_attrs]
    if missing:
        raise ProtocolError(
            f"attrs lack {' and '.join(missing)} (the replay buffer was ingested before carp recorded them; run "
            "the ingest stage again)"
        )
    return {
        "format": PROTOCOL_FORMAT,
        "observations": "state" if image_encoder is None else "image",
        "obs_keys": [str(key) for key in buffer_attrs["obs_keys"]],
        "obs_widths": [int(width) for width in buffer_attrs["obs_widths"]],
        "obs_steps": data.obs_steps,
        "action_horizon": data.action_horizon,
        "action_steps": data.action_steps,
        "cameras": [] if image_encoder is None else list(image_encoder.cameras),
        "image_size": None if image_encoder is None else image_encoder.image_size,
        **({} if control_frequency_hz is None else {"control_frequency_hz": int(control_frequency_hz)}),
    }


def recorded_protocol(metadata: Mapping[str, Any]) -> Mapping[str, Any] | None:
    """The protocol a checkpoint's metadata records, or None for a checkpoint trained before it was recorded."""
    protocol = metadata.get(SERVING_METADATA_KEY)
    return protocol if isinstance(protocol, Mapping) else None
