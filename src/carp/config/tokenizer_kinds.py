"""The params sections of the action tokenizer kinds, one top-level ``tokenizer_<kind>`` section each, and their names.

This is the light half of the kind table: the names here match `carp.tokenizer.kinds.registry.KIND_MODULES`, which
imports the implementations, so validating a params file never imports torch or a tokenizer. ``carp_msvq`` (the
default) keeps its settings in ``scales``, ``codebook_size`` and the ``tokenizer`` section; its own section
``tokenizer_carp_msvq`` is empty and exists so that the ``train_tokenizer`` stage can track
``tokenizer_${tokenizer.kind}`` whichever kind is selected (DVC refuses a tracked key that is missing from the file).
"""

import math
from dataclasses import dataclass

from carp.config.checks import _require, require_positive_int

DEFAULT_TOKENIZER_KIND = "carp_msvq"
TOKENIZER_KINDS = (DEFAULT_TOKENIZER_KIND, "binning", "fast", "bspline", "fsq", "joint_msvq", "residual_vq")
"""Every registered kind, the default first."""


def kind_section(kind: str) -> str:
    """The top-level params section of ``kind``: ``tokenizer_<kind>``."""
    return f"tokenizer_{kind}"


def _require_divides_horizon(key: str, downsampling: int, action_horizon: int) -> None:
    _require(
        action_horizon % downsampling == 0, key, downsampling, f"must divide data.action_horizon = {action_horizon}"
    )


def _require_percentiles(section: str, lower: float, upper: float) -> None:
    _require(0.0 <= lower < 50.0, f"{section}.lower_percentile", lower, "must be in [0, 50)")
    _require(50.0 < upper <= 100.0, f"{section}.upper_percentile", upper, "must be in (50, 100]")


@dataclass(frozen=True)
class CarpMsvqConfig:
    """CARP's kind has no settings here: they are ``scales``, ``codebook_size`` and the ``tokenizer`` section.

    The section is empty so that the ``train_tokenizer`` stage can track ``tokenizer_<kind>`` for every kind.
    """


@dataclass(frozen=True)
class BinningConfig:
    """Uniform binning of every step and dimension (RT-2, OpenVLA; `carp.tokenizer.kinds.binning`).

    Attributes:
        bins: ``N``, bins per action dimension, which is also the vocabulary; an integer >= 2.
        lower_percentile: Percentile of a dimension's training actions where its bins start; a number in [0, 50).
        upper_percentile: Percentile where its bins end; a number in (50, 100]. Values outside the range fall into
            the end bins.
    """

    bins: int = 256
    lower_percentile: float = 1.0
    upper_percentile: float = 99.0

    def __post_init__(self) -> None:
        _require(
            isinstance(self.bins, int) and self.bins >= 2,
            "tokenizer_binning.bins",
            self.bins,
            "must be an integer >= 2",
        )
        _require_percentiles("tokenizer_binning", self.lower_percentile, self.upper_percentile)


@dataclass(frozen=True)
class FastConfig:
    """DCT over time, scaled and rounded, then byte-pair encoded (FAST; `carp.tokenizer.kinds.fast`).

    Attributes:
        scale: Multiplies the orthonormal DCT coefficients of a normalized chunk before rounding; a number > 0.
            Larger keeps more precision and gives longer token sequences.
        vocabulary_size: Tokens of the byte-pair encoding trained on the training windows; an integer >= 2, and at
            least the number of distinct rounded coefficients (checked when it is fitted).
    """

    scale: float = 10.0
    vocabulary_size: int = 1024

    def __post_init__(self) -> None:
        _require(self.scale > 0, "tokenizer_fast.scale", self.scale, "must be > 0")
        _require(
            isinstance(self.vocabulary_size, int) and self.vocabulary_size >= 2,
            "tokenizer_fast.vocabulary_size",
            self.vocabulary_size,
            "must be an integer >= 2",
        )


@dataclass(frozen=True)
class BSplineConfig:
    """Quantized control points of a clamped uniform B-spline per dimension (BEAST; `carp.tokenizer.kinds.bspline`).

    Attributes:
        control_points: ``K``, control points per action dimension (tokens per dimension); an integer >= degree + 1
            and at most ``data.action_horizon`` (checked with the params when this kind is selected).
        degree: Degree of the spline; an integer >= 1.
        bins: Bins per control point, which is also the vocabulary; an integer >= 2. They span each dimension's
            control-point range on the training windows.
    """

    control_points: int = 8
    degree: int = 3
    bins: int = 256

    def __post_init__(self) -> None:
        require_positive_int("tokenizer_bspline.degree", self.degree)
        _require(
            isinstance(self.control_points, int) and self.control_points >= self.degree + 1,
            "tokenizer_bspline.control_points",
            self.control_points,
            f"must be an integer >= degree + 1 = {self.degree + 1}",
        )
        _require(
            isinstance(self.bins, int) and self.bins >= 2,
            "tokenizer_bspline.bins",
            self.bins,
            "must be an integer >= 2",
        )

    def check_horizon(self, action_horizon: int) -> None:
        """Refuse more control points than steps per chunk (`Params` calls it when this kind is selected)."""
        _require(
            self.control_points <= action_horizon,
            "tokenizer_bspline.control_points",
            self.control_points,
            f"must be at most data.action_horizon = {action_horizon}",
        )


@dataclass(frozen=True)
class FsqConfig:
    """Finite scalar quantization of a downsampled latent over all dimensions (QueST; `carp.tokenizer.kinds.fsq`).

    Attributes:
        levels: Values each latent channel is rounded to, one entry per channel; integers >= 2. The vocabulary is
            their product (240 for [8, 6, 5]).
        downsampling: ``H`` over tokens per chunk; a power of two that divides ``data.action_horizon`` (checked with
            the params when this kind is selected).
        hidden_channels: Width of the encoder's and decoder's convolutions; an integer >= 1.
        steps: Adam steps of training; an integer >= 1.
        batch_size: Windows per step; an integer >= 1.
        learning_rate: Adam's learning rate; a number > 0.
        seed: Seeds the initialization and the batches; any integer.
    """

    levels: tuple[int, ...] = (8, 6, 5)
    downsampling: int = 4
    hidden_channels: int = 32
    steps: int = 2000
    batch_size: int = 256
    learning_rate: float = 1e-3
    seed: int = 0

    def __post_init__(self) -> None:
        _require(
            len(self.levels) >= 1 and all(isinstance(level, int) and level >= 2 for level in self.levels),
            "tokenizer_fsq.levels",
            list(self.levels),
            "must be a non-empty list of integers >= 2",
        )
        _require(
            isinstance(self.downsampling, int) and self.downsampling >= 1 and math.log2(self.downsampling).is_integer(),
            "tokenizer_fsq.downsampling",
            self.downsampling,
            "must be a power of two",
        )
        for name in ("hidden_channels", "steps", "batch_size"):
            require_positive_int(f"tokenizer_fsq.{name}", getattr(self, name))
        _require(self.learning_rate > 0, "tokenizer_fsq.learning_rate", self.learning_rate, "must be > 0")

    def check_horizon(self, action_horizon: int) -> None:
        """Refuse a downsampling that does not divide the chunk (`Params` calls it when this kind is selected)."""
        _require_divides_horizon("tokenizer_fsq.downsampling", self.downsampling, action_horizon)


@dataclass(frozen=True)
class JointMsvqConfig:
    """One multi-scale residual VQ-VAE over all action dimensions jointly (`carp.tokenizer.kinds.joint_msvq`).

    Attributes:
        scales: Tokens per chunk at each scale, coarse to fine; strictly increasing positive integers, the last at
            most ``data.action_horizon``.
        codebook_size: Codes of the single codebook, which is also the vocabulary; an integer >= 2.
        latent_channels: Channels of a latent position and of a code; an integer >= 1.
        downsampling: The encoder's temporal downsampling; a power of two >= 2 that divides ``data.action_horizon``
            (checked with the params when this kind is selected).
        hidden_channels: Width of the encoder's and decoder's convolutions; an integer >= 1.
        commitment_weight: Weight of the commitment loss relative to the reconstruction loss; a number >= 0.
        steps: Adam steps of training; an integer >= 1.
        batch_size: Windows per step; an integer >= 1.
        learning_rate: Adam's learning rate; a number > 0.
        seed: Seeds the initialization, the batches and the code restarts; any integer.
    """

    scales: tuple[int, ...] = (1, 2, 3, 4)
    codebook_size: int = 512
    latent_channels: int = 8
    downsampling: int = 4
    hidden_channels: int = 32
    commitment_weight: float = 0.25
    steps: int = 2000
    batch_size: int = 256
    learning_rate: float = 1e-3
    seed: int = 0

    def __post_init__(self) -> None:
        _require(
            len(self.scales) >= 1
            and all(isinstance(scale, int) and scale >= 1 for scale in self.scales)
            and all(later > earlier for earlier, later in zip(self.scales, self.scales[1:], strict=False)),
            "tokenizer_joint_msvq.scales",
            list(self.scales),
            "must be strictly increasing positive integers",
        )
        _require(
            isinstance(self.codebook_size, int) and self.codebook_size >= 2,
            "tokenizer_joint_msvq.codebook_size",
            self.codebook_size,
            "must be an integer >= 2",
        )
        _require(
            isinstance(self.downsampling, int) and self.downsampling >= 2 and math.log2(self.downsampling).is_integer(),
            "tokenizer_joint_msvq.downsampling",
            self.downsampling,
            "must be a power of two >= 2",
        )
        for name in ("latent_channels", "hidden_channels", "steps", "batch_size"):
            require_positive_int(f"tokenizer_joint_msvq.{name}", getattr(self, name))
        _require(
            self.commitment_weight >= 0,
            "tokenizer_joint_msvq.commitment_weight",
            self.commitment_weight,
            "must be >= 0",
        )
        _require(self.learning_rate > 0, "tokenizer_joint_msvq.learning_rate", self.learning_rate, "must be > 0")

    def check_horizon(self, action_horizon: int) -> None:
        """Refuse a downsampling that does not divide the chunk (`Params` calls it when this kind is selected)."""
        _require_divides_horizon("tokenizer_joint_msvq.downsampling", self.downsampling, action_horizon)


@dataclass(frozen=True)
class ResidualVqConfig:
    """VQ-BeT's residual VQ over a whole chunk: one code per layer (`carp.tokenizer.kinds.residual_vq`).

    The defaults are VQ-BeT's (2 layers of 16 codes, 128-wide MLPs); the `vq_bet` family's VQ-VAE settings take
    them as their defaults too.

    Attributes:
        num_layers: ``R``, residual layers, which is also the number of tokens per chunk; an integer >= 1.
        num_codes: ``N``, codes per layer, which is also the vocabulary; an integer >= 2.
        latent_width: Width of the latent and of every code; an integer >= 1.
        hidden_width: Width of the hidden layers of the MLP encoder and decoder; an integer >= 1.
        codebook_decay: EMA decay of the codebooks per step; a number in (0, 1).
        commitment_weight: Weight of the commitment loss (summed over the residual layers) next to the L1
            reconstruction; a number >= 0.
        steps: Adam steps of training; an integer >= 1.
        batch_size: Windows per step; an integer >= 1.
        learning_rate: Adam's learning rate; a number > 0.
        weight_decay: Adam's (L2) weight decay; a number >= 0.
        seed: Seeds the initialization, the first codes and the batches; any integer.
    """

    num_layers: int = 2
    num_codes: int = 16
    latent_width: int = 256
    hidden_width: int = 128
    codebook_decay: float = 0.8
    commitment_weight: float = 5.0
    steps: int = 20000
    batch_size: int = 256
    learning_rate: float = 1e-3
    weight_decay: float = 1e-4
    seed: int = 0

    def __post_init__(self) -> None:
        section = kind_section("residual_vq")
        for name in ("num_layers", "latent_width", "hidden_width", "steps", "batch_size"):
            require_positive_int(f"{section}.{name}", getattr(self, name))
        _require(
            isinstance(self.num_codes, int) and self.num_codes >= 2,
            f"{section}.num_codes",
            self.num_codes,
            "must be an integer >= 2",
        )
        _require(0.0 < self.codebook_decay < 1.0, f"{section}.codebook_decay", self.codebook_decay, "must be in (0, 1)")
        _require(self.commitment_weight >= 0, f"{section}.commitment_weight", self.commitment_weight, "must be >= 0")
        _require(self.learning_rate > 0, f"{section}.learning_rate", self.learning_rate, "must be > 0")
        _require(self.weight_decay >= 0, f"{section}.weight_decay", self.weight_decay, "must be >= 0")
