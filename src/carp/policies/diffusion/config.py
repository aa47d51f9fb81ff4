"""Configs of the two Diffusion Policy families, one frozen dataclass each, validated at construction.

Each config is the family's params section (`diffusion_unet`, `diffusion_transformer`) and what its checkpoint
stores: the denoiser's shape, the training noise schedule, and DP's optimizer and EMA recipe. The inference sampler
is the separate section `inference.<family>` (:class:`SamplingConfig`): it changes evaluation only, so DVC reruns
evaluation and not training when it changes. Shapes that come from the data (`Do`, `To`, `H`, `A`) are passed to the
models separately. Loop settings shared by every family (epochs, batch size, checkpoints, seed) are the `training`
section. Defaults are those of the official lowdim
configs (`train_diffusion_unet_lowdim_workspace.yaml`, `train_diffusion_transformer_lowdim_workspace.yaml`).
"""

from dataclasses import dataclass, fields
from typing import Any, ClassVar

from carp.config.checks import _require, require_optimizer_settings, require_positive_int

SAMPLERS = ("ddpm", "ddim")


@dataclass(frozen=True)
class UNetSettings:
    """The size of the DP-C U-Net (`carp.policies.diffusion.unet`), written once for the three families that train it.

    `diffusion_unet`, the Consistency Policy teacher `edm_unet` and its student `consistency_policy` share these
    fields, their defaults and their checks. ``down_dims: [64, 128, 256]`` is the CPU-sized variant (5.4 M parameters
    on Can's shapes against 65.9 M at the defaults; the count does not depend on the horizon).

    Attributes:
        down_dims: Channels of each U-Net level, finest first; one level per entry, each entry an integer >= 1
            divisible by ``num_groups``. The horizon must be divisible by ``2 ** (len(down_dims) - 1)``.
        kernel_size: Temporal kernel of the residual blocks' convolutions; an odd integer >= 1 (odd keeps the
            horizon unchanged with symmetric padding).
        num_groups: GroupNorm groups of every convolution block; an integer >= 1.
        step_embedding_dim: Width of the sinusoidal diffusion-step (noise-level) embedding and of the MLP that
            follows it; an even integer >= 4.
    """

    down_dims: tuple[int, ...] = (256, 512, 1024)
    kernel_size: int = 5
    num_groups: int = 8
    step_embedding_dim: int = 256

    def check_unet(self, section: str) -> None:
        """Validate the U-Net fields, naming them under `section`; a `down_dims` list from YAML becomes a tuple."""
        object.__setattr__(self, "down_dims", tuple(self.down_dims))
        _require(len(self.down_dims) >= 1, f"{section}.down_dims", self.down_dims, "must name at least one level")
        for channels in self.down_dims:
            require_positive_int(f"{section}.down_dims", channels)
        require_positive_int(f"{section}.num_groups", self.num_groups)
        _require(
            all(channels % self.num_groups == 0 for channels in self.down_dims),
            f"{section}.num_groups",
            self.num_groups,
            f"must divide every entry of down_dims={list(self.down_dims)}",
        )
        require_positive_int(f"{section}.kernel_size", self.kernel_size)
        _require(self.kernel_size % 2 == 1, f"{section}.kernel_size", self.kernel_size, "must be odd")
        require_positive_int(f"{section}.step_embedding_dim", self.step_embedding_dim)
        _require(
            self.step_embedding_dim >= 4 and self.step_embedding_dim % 2 == 0,
            f"{section}.step_embedding_dim",
            self.step_embedding_dim,
            "must be an even integer >= 4",
        )

    @property
    def horizon_multiple(self) -> int:
        """The horizon must be a multiple of this: each U-Net level but the coarsest halves it."""
        return 2 ** (len(self.down_dims) - 1)


UNET_FIELDS = tuple(entry.name for entry in fields(UNetSettings))
"""The names of the U-Net's fields, which a distilled student must share with its teacher."""


@dataclass(frozen=True)
class DenoisingConfig:
    """Noise schedule, optimizer and EMA fields shared by both Diffusion Policy families.

    The schedule itself is fixed to DP's: squared-cosine betas (`squaredcos_cap_v2`), epsilon prediction, denoised
    estimates clipped to [-1, 1] (actions are min-max normalized to that range). See `carp.policies.diffusion.sampler`.

    Attributes:
        num_train_steps: Diffusion steps of the training noise schedule (DP: 100); an integer >= 1.
        learning_rate: Peak AdamW learning rate, reached after a linear warm-up and followed by a cosine decay to 1%
            of the peak; a number > 0.
        weight_decay: AdamW weight decay of the weight matrices; a number >= 0.
        warmup_steps: Optimizer steps of linear learning-rate warm-up before the cosine decay; an integer >= 0.
        use_ema: Evaluate an exponential moving average of the weights, as DP does (see
            `carp.policies.diffusion.ema`); true or false.
        ema_power: Exponent of the EMA warm-up: the decay after n updates is ``1 - n ** -ema_power``, capped at
            ``ema_max_decay``; a number in (0, 1].
        ema_max_decay: Largest EMA decay; a number in [0, 1).
    """

    SECTION: ClassVar[str] = "diffusion"

    num_train_steps: int = 100
    learning_rate: float = 1e-4
    weight_decay: float = 1e-6
    warmup_steps: int = 500
    use_ema: bool = True
    ema_power: float = 0.75
    ema_max_decay: float = 0.9999

    def __post_init__(self) -> None:
        section = self.SECTION
        require_positive_int(f"{section}.num_train_steps", self.num_train_steps)
        require_optimizer_settings(section, self)
        _require(0.0 < self.ema_power <= 1.0, f"{section}.ema_power", self.ema_power, "must be in (0, 1]")
        _require(0.0 <= self.ema_max_decay < 1.0, f"{section}.ema_max_decay", self.ema_max_decay, "must be in [0, 1)")


@dataclass(frozen=True)
class SamplingConfig:
    """How a Diffusion Policy family denoises at evaluation (the section `inference.<family>`).

    Attributes:
        sampler: ``ddpm`` (DP's protocol: ancestral sampling) or ``ddim`` (deterministic given the initial noise, so
            fewer steps suffice). The report names each row's sampler, e.g. ``DDPM-100`` or ``DDIM-10``.
        num_inference_steps: Denoiser calls per action chunk; an integer between 1 and the family's
            ``num_train_steps``. DDPM with fewer steps than training strides the schedule.
    """

    SECTION: ClassVar[str] = "diffusion"

    sampler: str = "ddpm"
    num_inference_steps: int = 100

    def __post_init__(self) -> None:
        key = f"inference.{self.SECTION}"
        _require(self.sampler in SAMPLERS, f"{key}.sampler", self.sampler, f"must be one of {SAMPLERS}")
        require_positive_int(f"{key}.num_inference_steps", self.num_inference_steps)

    def settings_for(self, task: str) -> dict[str, Any]:
        """Keyword arguments of `DiffusionPolicy.configure_inference` (the same for every task)."""
        return {"sampler": self.sampler, "num_inference_steps": self.num_inference_steps}

    def check_with(self, params: Any) -> None:
        """Refuse more denoising steps than the family's training schedule has."""
        train_steps = params.family_config(self.SECTION).num_train_steps
        _require(
            self.num_inference_steps <= train_steps,
            f"inference.{self.SECTION}.num_inference_steps",
            self.num_inference_steps,
            f"must be at most {self.SECTION}.num_train_steps={train_steps}",
        )


@dataclass(frozen=True)
class DiffusionUNetSampling(SamplingConfig):
    """How DP-C denoises at evaluation (``inference.diffusion_unet``); see :class:`SamplingConfig`.

    Attributes:
        sampler: ``ddpm`` (DP's protocol: ancestral sampling) or ``ddim`` (deterministic given the initial noise, so
            fewer steps suffice). At paper size DDPM-100 costs seconds per chunk on a CPU core; DDIM-10 is the
            CPU-friendly alternative, and the report names each row's sampler.
        num_inference_steps: Denoiser calls per action chunk; an integer between 1 and
            ``diffusion_unet.num_train_steps``.
    """

    SECTION: ClassVar[str] = "diffusion_unet"


@dataclass(frozen=True)
class DiffusionTransformerSampling(SamplingConfig):
    """How DP-T denoises at evaluation (``inference.diffusion_transformer``); see :class:`SamplingConfig`.

    Attributes:
        sampler: ``ddpm`` (DP's protocol: ancestral sampling) or ``ddim`` (deterministic given the initial noise, so
            fewer steps suffice); the report names each row's sampler.
        num_inference_steps: Denoiser calls per action chunk; an integer between 1 and
            ``diffusion_transformer.num_train_steps``.
    """

    SECTION: ClassVar[str] = "diffusion_transformer"


@dataclass(frozen=True)
class DiffusionUNetConfig(DenoisingConfig, UNetSettings):
    """DP-C: the 1-D temporal convolutional U-Net with FiLM conditioning (`carp.policies.diffusion.unet`).

    The schedule, learning rate and EMA fields are :class:`DenoisingConfig`'s, the U-Net's :class:`UNetSettings`'.

    Attributes:
        weight_decay: AdamW weight decay of the weight matrices; a number >= 0 (DP's default: 1e-6).
        warmup_steps: Optimizer steps of linear learning-rate warm-up before the cosine decay; an integer >= 0
            (DP's default: 500).
    """

    SECTION: ClassVar[str] = "diffusion_unet"

    def __post_init__(self) -> None:
        super().__post_init__()
        self.check_unet(self.SECTION)


@dataclass(frozen=True)
class DiffusionTransformerConfig(DenoisingConfig):
    """DP-T: the transformer denoiser with causal self-attention (`carp.policies.diffusion.transformer`).

    At the defaults and Can's shapes (Do = 23, To = 2, A = 10) it has 8,968,458 parameters (9.0 M) at DP's robomimic
    horizon H = 10 and 8,969,994 at H = 16: only the action position embedding grows, by `width` per action.

    The schedule, learning rate and EMA fields are :class:`DenoisingConfig`'s.

    Attributes:
        weight_decay: AdamW weight decay of the weight matrices; a number >= 0 (DP's default: 1e-3).
        warmup_steps: Optimizer steps of linear learning-rate warm-up before the cosine decay; an integer >= 0
            (DP's default: 1000).
        num_layers: Transformer decoder layers of the denoiser; an integer >= 1.
        num_heads: Attention heads of every layer; an integer >= 1 dividing ``width``.
        width: Token width of the action and condition tokens; an integer >= 1.
        embedding_dropout: Dropout on the token and condition embeddings during training; a number in [0, 1).
        attention_dropout: Dropout inside every decoder layer (attention weights, residual branches) during training;
            a number in [0, 1).
    """

    SECTION: ClassVar[str] = "diffusion_transformer"

    weight_decay: float = 1e-3
    warmup_steps: int = 1000
    num_layers: int = 8
    num_heads: int = 4
    width: int = 256
    embedding_dropout: float = 0.0
    attention_dropout: float = 0.3

    def __post_init__(self) -> None:
        super().__post_init__()
        section = self.SECTION
        require_positive_int(f"{section}.num_layers", self.num_layers)
        require_positive_int(f"{section}.num_heads", self.num_heads)
        require_positive_int(f"{section}.width", self.width)
        _require(
            self.width % self.num_heads == 0,
            f"{section}.num_heads",
            self.num_heads,
            f"must divide width={self.width}",
        )
        for name in ("embedding_dropout", "attention_dropout"):
            value = getattr(self, name)
            _require(0.0 <= value < 1.0, f"{section}.{name}", value, "must be in [0, 1)")


UNET_SECTIONS = (DiffusionUNetConfig, DiffusionUNetSampling)
TRANSFORMER_SECTIONS = (DiffusionTransformerConfig, DiffusionTransformerSampling)
"""The registry's view of this module: each family's section and its `inference.<family>` section."""
