"""Architecture of the multi-scale action tokenizer, validated when it is built.

The spec holds only what fixes the tensor shapes and the math (it is stored inside every tokenizer checkpoint so a
checkpoint rebuilds its own module); training settings live in `carp.training.tokenizer_trainer`.
"""

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any


def _require_int(field_name: str, value: Any, minimum: int) -> None:
    # bool is an int subclass; `True` as a size is always a typo in a config file.
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{field_name} must be an integer, got {value!r}")
    if value < minimum:
        raise ValueError(f"{field_name} must be >= {minimum}, got {value}")


@dataclass(frozen=True)
class TokenizerSpec:
    """Shape-defining settings of the per-dimension multi-scale residual VQ-VAE.

    Its place in the tokenizer: docs/architecture.md, "Action tokenizer".

    Attributes:
        action_dim: A, number of action dimensions; each gets its own encoder, decoder, codebook and phi convs.
        action_horizon: H, steps per action chunk; must be divisible by 2 ** len(channel_mult).
        scales: s_1..s_K, tokens per dimension at each scale: strictly increasing positive sizes, the last at most H.
            A last scale below the encoder's output length reconstructs from coarser maps only; one above it gets a
            latent of its own length (see ``latent_length``).
        codebook_size: V, codes per dimension's codebook.
        latent_channels: C, channels of a latent position and of a code.
        base_channels: ch, channels after the encoder's input convolution.
        channel_mult: channel multiplier of each down-sampling level (channels = ch * mult).
        commitment_weight: beta, weight of the commitment term that pulls the encoder towards its codes.
    """

    action_dim: int
    action_horizon: int = 16
    scales: tuple[int, ...] = (1, 2, 3, 4)
    codebook_size: int = 512
    latent_channels: int = 8
    base_channels: int = 2
    channel_mult: tuple[int, ...] = (2, 4)
    commitment_weight: float = 0.25

    def __post_init__(self) -> None:
        # YAML and JSON hand over lists; the frozen spec keeps tuples so it stays hashable and comparable.
        object.__setattr__(self, "scales", tuple(self.scales))
        object.__setattr__(self, "channel_mult", tuple(self.channel_mult))
        _require_int("action_dim", self.action_dim, 1)
        _require_int("action_horizon", self.action_horizon, 1)
        _require_int("codebook_size", self.codebook_size, 2)
        _require_int("latent_channels", self.latent_channels, 1)
        _require_int("base_channels", self.base_channels, 1)
        if not self.channel_mult:
            raise ValueError("channel_mult must name at least one down-sampling level")
        for multiplier in self.channel_mult:
            _require_int("channel_mult entries", multiplier, 1)
        stride = 2 ** len(self.channel_mult)
        if self.action_horizon % stride != 0:
            raise ValueError(
                f"action_horizon ({self.action_horizon}) must be divisible by 2 ** len(channel_mult) = {stride}"
            )
        if not self.scales:
            raise ValueError("scales must contain at least one scale")
        for scale in self.scales:
            _require_int("scales entries", scale, 1)
        if any(later <= earlier for earlier, later in zip(self.scales, self.scales[1:], strict=False)):
            raise ValueError(f"scales must be strictly increasing, got {list(self.scales)}")
        if self.scales[-1] > self.action_horizon:
            raise ValueError(
                f"scales must end at most at the action horizon {self.action_horizon} (one token per action step), "
                f"got last scale {self.scales[-1]}"
            )
        if isinstance(self.commitment_weight, bool) or not isinstance(self.commitment_weight, int | float):
            raise ValueError(f"commitment_weight must be a number, got {self.commitment_weight!r}")
        if self.commitment_weight < 0:
            raise ValueError(f"commitment_weight must be >= 0, got {self.commitment_weight}")

    @property
    def encoder_length(self) -> int:
        """Positions per dimension of the encoder's output: H / 2 ** len(channel_mult)."""
        return self.action_horizon // 2 ** len(self.channel_mult)

    @property
    def latent_length(self) -> int:
        """l, positions per dimension of the latent the scales quantize.

        The encoder's length, or the last scale where that is longer (the encoder's output is then resampled up to
        it, and back before the decoder).
        """
        return max(self.encoder_length, self.scales[-1])

    @property
    def num_scales(self) -> int:
        """K, number of scales."""
        return len(self.scales)

    @property
    def tokens_per_chunk(self) -> int:
        """L = A * sum(s_k), tokens of one action chunk over all scales and dimensions."""
        return self.action_dim * sum(self.scales)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON/YAML-friendly dict (tuples become lists)."""
        values = asdict(self)
        values["scales"] = list(self.scales)
        values["channel_mult"] = list(self.channel_mult)
        return values

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "TokenizerSpec":
        """Build a spec from `to_dict` output; unknown keys are errors, missing keys take the defaults."""
        known = {field.name for field in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown TokenizerSpec keys: {unknown}")
        return cls(**values)
