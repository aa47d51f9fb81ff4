"""Consistency Policy's params sections: teacher (`edm_unet`), student (`consistency_policy`), inference sections.

Defaults follow the official configs (`configs/edm_square.yaml`, `configs/ctmp_square.yaml`): noise levels in
[0.02, 80] with rho 7 and sigma_data 0.5, 80 levels, log-normal training levels (mean -1.2, std 1.2), the Heun
solver, boundary-condition scalings; the student distils with the consistency-trajectory loss plus the denoising
loss (weights 1 and 1), at most one teacher step per sample, a target network that is the student's own weights
(EMA decay 0), and AdamW at 1e-4 with DP's EMA for evaluation. The U-Net is DP-C's at its default size
(`carp.policies.diffusion.unet`); the official image configs widen it, carp keeps DP-C's so that the comparison with
`diffusion_unet` is like for like. On a CPU, ``down_dims: [64, 128, 256]`` in both sections is the documented recipe.
"""

from dataclasses import dataclass
from typing import Any, ClassVar

from carp.config.checks import _require, require_optimizer_settings, require_positive_int
from carp.policies.diffusion.config import UNET_FIELDS, UNetSettings

TEACHER = "edm_unet"
STUDENT = "consistency_policy"


def _plain(value: Any) -> Any:
    """A tuple as the list YAML wrote, for messages."""
    return list(value) if isinstance(value, tuple) else value


def _check_ema(section: str, config: Any) -> None:
    _require(0.0 < config.ema_power <= 1.0, f"{section}.ema_power", config.ema_power, "must be in (0, 1]")
    _require(0.0 <= config.ema_max_decay < 1.0, f"{section}.ema_max_decay", config.ema_max_decay, "must be in [0, 1)")


@dataclass(frozen=True)
class EDMConfig(UNetSettings):
    """The teacher: DP-C's U-Net trained as an EDM denoiser (`carp.policies.consistency.teacher`).

    At the defaults it has the parameters of `diffusion_unet` at its defaults (65.9 M on Can).

    Attributes:
        learning_rate: Peak AdamW learning rate (betas 0.95, 0.999), after a linear warm-up and followed by a cosine
            decay to 1% of the peak; a number > 0.
        weight_decay: AdamW weight decay; a number >= 0.
        warmup_steps: Optimizer steps of linear learning-rate warm-up; an integer >= 0.
        use_ema: Evaluate (and distil from) DP's exponential moving average of the weights; true or false.
        ema_power: Exponent of the EMA warm-up: the decay after n updates is ``1 - n ** -ema_power``, capped at
            ``ema_max_decay``; a number in (0, 1].
        ema_max_decay: Largest EMA decay; a number in [0, 1).
        sigma_min: Smallest noise level; the denoiser is the identity there; a number > 0.
        sigma_max: Largest noise level, where sampling starts; a number > sigma_min.
        rho: Curvature of the discretization of the noise levels; a number > 0.
        sigma_data: Standard deviation assumed for the normalized actions (they lie in [-1, 1]); a number > 0.
        log_sigma_mean: Mean of ln(sigma) of the training noise levels (EDM's P_mean); a number.
        log_sigma_std: Standard deviation of ln(sigma) of the training noise levels (EDM's P_std); a number > 0.
    """

    SECTION: ClassVar[str] = TEACHER

    learning_rate: float = 1e-4
    weight_decay: float = 1e-6
    warmup_steps: int = 500
    use_ema: bool = True
    ema_power: float = 0.75
    ema_max_decay: float = 0.9999
    sigma_min: float = 0.02
    sigma_max: float = 80.0
    rho: float = 7.0
    sigma_data: float = 0.5
    log_sigma_mean: float = -1.2
    log_sigma_std: float = 1.2

    def __post_init__(self) -> None:
        section = self.SECTION
        require_optimizer_settings(section, self)
        _check_ema(section, self)
        self.check_unet(section)
        _require(self.sigma_min > 0, f"{section}.sigma_min", self.sigma_min, "must be > 0")
        _require(
            self.sigma_max > self.sigma_min,
            f"{section}.sigma_max",
            self.sigma_max,
            f"must be > sigma_min={self.sigma_min}",
        )
        for name in ("rho", "sigma_data", "log_sigma_std"):
            value = getattr(self, name)
            _require(value > 0, f"{section}.{name}", value, "must be > 0")


@dataclass(frozen=True)
class EDMSampling:
    """How the EDM teacher samples at evaluation (``inference.edm_unet``).

    Attributes:
        num_levels: Noise levels of the Heun solver, from sigma_max down to sigma_min; 2 * (num_levels - 1)
            denoiser calls per chunk (the official 80 levels: 158 calls); an integer >= 2.
    """

    SECTION: ClassVar[str] = TEACHER

    num_levels: int = 80

    def __post_init__(self) -> None:
        key = f"inference.{self.SECTION}.num_levels"
        require_positive_int(key, self.num_levels)
        _require(self.num_levels >= 2, key, self.num_levels, "must be >= 2")

    def settings_for(self, task: str) -> dict[str, Any]:
        """Keyword arguments of `EDMPolicy.configure_inference` (the same for every task)."""
        return {"num_levels": self.num_levels}


@dataclass(frozen=True)
class ConsistencyConfig(UNetSettings):
    """The student: the teacher's U-Net with a second noise-level input, distilled (`carp.policies.consistency`).

    Its U-Net fields must equal the teacher's (``edm_unet``), whose weights it starts from; the noise-level range
    and preconditioning are the teacher's. It has the teacher's parameters plus one step embedding's worth of
    columns in every FiLM projection.

    Attributes:
        learning_rate: Peak AdamW learning rate (betas 0.95, 0.999), after a linear warm-up and followed by a cosine
            decay to 1% of the peak; a number > 0.
        weight_decay: AdamW weight decay; a number >= 0.
        warmup_steps: Optimizer steps of linear learning-rate warm-up; an integer >= 0.
        use_ema: Evaluate DP's exponential moving average of the student's weights; true or false.
        ema_power: Exponent of the evaluation EMA's warm-up; a number in (0, 1].
        ema_max_decay: Largest decay of the evaluation EMA; a number in [0, 1).
        down_dims: As ``edm_unet.down_dims``, which it must equal.
        kernel_size: As ``edm_unet.kernel_size``, which it must equal.
        num_groups: As ``edm_unet.num_groups``, which it must equal.
        step_embedding_dim: As ``edm_unet.step_embedding_dim``, which it must equal.
        num_levels: Noise levels of the discretization the consistency-trajectory loss draws its start, middle and
            target levels from; an integer >= 2.
        teacher_steps: Most Heun steps of the teacher from the start level towards the middle level per sample
            (the official ``ode_steps_max``); an integer >= 1.
        target_decay: EMA decay per optimizer step of the target network the loss compares against; 0 makes it the
            student's current weights without gradient (the official setting); a number in [0, 1).
        trajectory_weight: Weight of the consistency-trajectory loss; a number >= 0.
        denoising_weight: Weight of the denoising loss (the student's denoiser at its own level against the clean
            chunk), relative to the trajectory loss: 1 gives both the same gradient norm at the U-Net's output
            layer (CTM's adaptive weight); a number >= 0, and not both weights 0.
    """

    SECTION: ClassVar[str] = STUDENT
    TEACHER: ClassVar[str] = TEACHER  # the family whose trained policy this one distils, trained first

    learning_rate: float = 1e-4
    weight_decay: float = 1e-6
    warmup_steps: int = 500
    use_ema: bool = True
    ema_power: float = 0.75
    ema_max_decay: float = 0.9999
    num_levels: int = 80
    teacher_steps: int = 1
    target_decay: float = 0.0
    trajectory_weight: float = 1.0
    denoising_weight: float = 1.0

    def __post_init__(self) -> None:
        section = self.SECTION
        require_optimizer_settings(section, self)
        _check_ema(section, self)
        self.check_unet(section)
        require_positive_int(f"{section}.num_levels", self.num_levels)
        _require(self.num_levels >= 2, f"{section}.num_levels", self.num_levels, "must be >= 2")
        require_positive_int(f"{section}.teacher_steps", self.teacher_steps)
        _require(0.0 <= self.target_decay < 1.0, f"{section}.target_decay", self.target_decay, "must be in [0, 1)")
        for name in ("trajectory_weight", "denoising_weight"):
            value = getattr(self, name)
            _require(value >= 0, f"{section}.{name}", value, "must be >= 0")
        _require(
            self.trajectory_weight + self.denoising_weight > 0,
            f"{section}.denoising_weight",
            self.denoising_weight,
            "must be > 0 when trajectory_weight is 0",
        )

    def check_with(self, params: Any) -> None:
        """Refuse a U-Net that differs from the teacher's (the student's stage trains its teacher from ``edm_unet``)."""
        teacher = params.family_config(TEACHER)
        for name in UNET_FIELDS:
            ours, theirs = _plain(getattr(self, name)), _plain(getattr(teacher, name))
            _require(
                ours == theirs, f"{self.SECTION}.{name}", ours, f"must equal the teacher's {TEACHER}.{name}={theirs}"
            )


@dataclass(frozen=True)
class ConsistencySampling:
    """How the student samples at evaluation (``inference.consistency_policy``).

    Attributes:
        chain_levels: Positions, in the student's ``num_levels`` discretization, of the levels a chained sample is
            re-noised to after the first step: [] is one-step sampling (one call per chunk); the official three-step
            chain is [27, 54] (noise levels 12.0 and 0.88 at the defaults). Strictly increasing, each between 1 and
            num_levels - 1.
    """

    SECTION: ClassVar[str] = STUDENT

    chain_levels: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "chain_levels", tuple(self.chain_levels))
        key = f"inference.{self.SECTION}.chain_levels"
        for position in self.chain_levels:
            require_positive_int(key, position)
        _require(
            all(a < b for a, b in zip(self.chain_levels, self.chain_levels[1:])),
            key,
            list(self.chain_levels),
            "must be strictly increasing",
        )

    def settings_for(self, task: str) -> dict[str, Any]:
        """Keyword arguments of `ConsistencyPolicy.configure_inference` (the same for every task)."""
        return {"chain_levels": self.chain_levels}

    def check_with(self, params: Any) -> None:
        """Refuse positions past the student's discretization."""
        num_levels = params.family_config(self.SECTION).num_levels
        _require(
            all(position < num_levels for position in self.chain_levels),
            f"inference.{self.SECTION}.chain_levels",
            list(self.chain_levels),
            f"every position must be below {self.SECTION}.num_levels={num_levels}",
        )


TEACHER_SECTIONS = (EDMConfig, EDMSampling)
STUDENT_SECTIONS = (ConsistencyConfig, ConsistencySampling)
"""The registry's view of this module: each family's section and its `inference.<family>` section."""
