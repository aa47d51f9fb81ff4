"""VQ-BeT's params sections: `vq_bet` (the VQ-VAE, the GPT, their losses and optimizers) and `inference.vq_bet`.

Defaults are those of VQ-BeT's public code for its state-based tasks (Push-T among them): a residual VQ-VAE of 2
layers x 16 codes with 128-wide MLPs, a GPT of 6 layers, 6 heads and width 120 with dropout 0.1, code and offset
heads with two 1024-wide hidden layers, focal loss (gamma 2) on the codes weighted 5 (primary) and 0.5 (secondary),
L1 on the offsets weighted 100, AdamW at 5.5e-5 with weight decay 2e-4 and betas (0.9, 0.95), and the GPT and code
head frozen after half of the epochs. The chunk length is the pipeline's `data.action_horizon` and the observation
window its `data.obs_steps`; the loop settings (epochs, batch size, seed) are the shared `training` section.
"""

from dataclasses import dataclass
from typing import Any, ClassVar

from carp.config.checks import _require, require_optimizer_settings, require_positive_int
from carp.config.tokenizer_kinds import ResidualVqConfig

SECTION = "vq_bet"
CODE_CHOICES = ("sample", "greedy")
# The VQ-VAE is the residual_vq tokenizer kind's network: its defaults have one home, that kind's section.
_VQ_VAE = ResidualVqConfig()


@dataclass(frozen=True)
class VqBetConfig:
    """VQ-BeT: its action VQ-VAE, trained first, then the GPT with code and offset heads.

    At the defaults, with Push-T's state (Do = 20, A = 2) and carp's protocol (To = 2, H = 16), the trained part
    (GPT and heads; the frozen VQ-VAE excluded) has 4,787,816 parameters; with VQ-BeT's own Push-T chunk of 5
    actions and window of 5 steps, 4,066,576; at H = 8, 4,263,016. See `carp.policies.vq_bet.transformer`.

    Attributes:
        num_codes: Codes per residual layer of the VQ-VAE; an integer >= 2.
        num_residual_layers: Residual quantizer layers, i.e. codes per chunk (the first is the primary code, the
            others secondary); an integer >= 1.
        latent_width: Width of the VQ-VAE latent and of every code; an integer >= 1.
        encoder_hidden_width: Width of the hidden layers of the VQ-VAE's MLP encoder and decoder; an integer >= 1.
        codebook_decay: EMA decay of the codebooks per VQ-VAE step; a number in (0, 1).
        commitment_weight: Weight of the commitment loss (summed over the layers) next to the L1 reconstruction; a
            number >= 0.
        vq_training_steps: Adam steps of the VQ-VAE phase, before the GPT trains; an integer >= 1.
        vq_batch_size: Action chunks per VQ-VAE step; an integer >= 1.
        vq_learning_rate: Adam learning rate of the VQ-VAE; a number > 0.
        vq_weight_decay: Adam weight decay of the VQ-VAE; a number >= 0.
        depth: GPT layers; an integer >= 1.
        num_heads: Attention heads per GPT layer; an integer >= 1 that divides ``width``.
        width: Token width of the GPT; an integer >= 1.
        dropout: Dropout of the GPT's embeddings, attention weights and residual branches during training; a number
            in [0, 1).
        output_width: Width of the GPT's output projection, the heads' input; an integer >= 1.
        head_hidden_width: Width of the two hidden layers of the code head and of the offset head; an integer >= 1.
        focal_gamma: Focusing exponent of the focal loss on the codes (0 = cross entropy); a number >= 0.
        primary_code_weight: Weight of the primary code's focal loss; a number >= 0.
        secondary_code_weight: Weight of the secondary codes' focal loss; a number >= 0.
        offset_weight: Weight of the offsets' L1 loss; a number >= 0.
        freeze_fraction: Share of the epochs after which the GPT and the code head stop training and only the offset
            head learns; a number in (0, 1], 1 = never freeze.
        learning_rate: Peak AdamW learning rate of the GPT phase (betas 0.9, 0.95), after a linear warm-up and
            followed by a cosine decay to 1% of the peak; a number > 0.
        weight_decay: AdamW weight decay of the GPT phase's weight matrices; a number >= 0.
        warmup_steps: Optimizer steps of linear learning-rate warm-up of the GPT phase; an integer >= 0.
        use_ema: Keep an exponential moving average of the GPT phase's weights and save it instead; true or false.
        ema_decay: Decay of that average per optimizer step, used only with ``use_ema``; a number in (0, 1).
    """

    num_codes: int = _VQ_VAE.num_codes
    num_residual_layers: int = _VQ_VAE.num_layers
    latent_width: int = _VQ_VAE.latent_width
    encoder_hidden_width: int = _VQ_VAE.hidden_width
    codebook_decay: float = _VQ_VAE.codebook_decay
    commitment_weight: float = _VQ_VAE.commitment_weight
    vq_training_steps: int = _VQ_VAE.steps
    vq_batch_size: int = _VQ_VAE.batch_size
    vq_learning_rate: float = _VQ_VAE.learning_rate
    vq_weight_decay: float = _VQ_VAE.weight_decay
    depth: int = 6
    num_heads: int = 6
    width: int = 120
    dropout: float = 0.1
    output_width: int = 256
    head_hidden_width: int = 1024
    focal_gamma: float = 2.0
    primary_code_weight: float = 5.0
    secondary_code_weight: float = 0.5
    offset_weight: float = 100.0
    freeze_fraction: float = 0.5
    learning_rate: float = 5.5e-5
    weight_decay: float = 2e-4
    warmup_steps: int = 0
    use_ema: bool = False
    ema_decay: float = 0.999

    SECTION: ClassVar[str] = SECTION

    def __post_init__(self) -> None:
        section = self.SECTION
        _require(
            isinstance(self.num_codes, int) and not isinstance(self.num_codes, bool) and self.num_codes >= 2,
            f"{section}.num_codes",
            self.num_codes,
            "must be an integer >= 2",
        )
        for name in (
            "num_residual_layers",
            "latent_width",
            "encoder_hidden_width",
            "vq_training_steps",
            "vq_batch_size",
            "depth",
            "num_heads",
            "width",
            "output_width",
            "head_hidden_width",
        ):
            require_positive_int(f"{section}.{name}", getattr(self, name))
        _require(
            self.width % self.num_heads == 0, f"{section}.num_heads", self.num_heads, f"must divide width={self.width}"
        )
        _require(0.0 < self.codebook_decay < 1.0, f"{section}.codebook_decay", self.codebook_decay, "must be in (0, 1)")
        _require(0.0 <= self.dropout < 1.0, f"{section}.dropout", self.dropout, "must be in [0, 1)")
        _require(self.vq_learning_rate > 0, f"{section}.vq_learning_rate", self.vq_learning_rate, "must be > 0")
        for name in (
            "commitment_weight",
            "vq_weight_decay",
            "focal_gamma",
            "primary_code_weight",
            "secondary_code_weight",
            "offset_weight",
        ):
            _require(getattr(self, name) >= 0, f"{section}.{name}", getattr(self, name), "must be >= 0")
        _require(
            0.0 < self.freeze_fraction <= 1.0, f"{section}.freeze_fraction", self.freeze_fraction, "must be in (0, 1]"
        )
        require_optimizer_settings(section, self)
        _require(0.0 < self.ema_decay < 1.0, f"{section}.ema_decay", self.ema_decay, "must be in (0, 1)")


@dataclass(frozen=True)
class VqBetInference:
    """How evaluation chooses VQ-BeT's codes; decoding only, so a change reruns evaluation, not training.

    Attributes:
        code_choice: ``sample`` draws each residual layer's code from the code head's softmax, with draws seeded per
            episode (VQ-BeT's inference); ``greedy`` takes the most likely code of each layer. The offset of the
            chosen codes is added either way.
    """

    code_choice: str = "sample"

    SECTION: ClassVar[str] = SECTION

    def __post_init__(self) -> None:
        key = f"inference.{self.SECTION}.code_choice"
        _require(self.code_choice in CODE_CHOICES, key, self.code_choice, f"must be one of {CODE_CHOICES}")

    def settings_for(self, task: str) -> dict[str, Any]:
        """Keyword arguments of `VqBetPolicy.configure_inference` (the same for every task)."""
        return {"code_choice": self.code_choice}


SECTIONS = (VqBetConfig, VqBetInference)
"""The registry's view of this module: the `vq_bet` and `inference.vq_bet` sections."""
