"""The `tokenizer` section: the kind, how the multi-scale kind is trained or where a registered one comes from."""

from dataclasses import dataclass

from carp.config.checks import REGISTRY_URI_PREFIX, _positive_training_fields, _require, require_registry_alias
from carp.config.tokenizer_kinds import DEFAULT_TOKENIZER_KIND, TOKENIZER_KINDS


@dataclass(frozen=True)
class TokenizerConfig:
    """The tokenizer kind; CARP's multi-scale VQ-VAE (docs/architecture.md, "Action tokenizer") and its training.

    The other kinds' settings are their own top-level sections ``tokenizer_<kind>``.

    Attributes:
        kind: The tokenizer kind, one of ``carp_msvq`` (CARP's per-dimension multi-scale VQ-VAE, which the other
            fields of this section and ``scales`` and ``codebook_size`` configure), ``binning``, ``fast``,
            ``bspline``, ``fsq`` and ``joint_msvq`` (each configured by its own top-level section
            ``tokenizer_<kind>``; docs/developing.md, "Tokenizer kinds"). The ``train_tokenizer`` stage trains and
            registers the selected kind and tracks only its section. The ``carp`` family needs ``carp_msvq``; the
            ``next_token`` family takes any kind.
        source: Where the tokenizer comes from: ``pipeline`` trains it here and registers it in the MLflow Model
            Registry; a registry URI ``models:/<name>@<alias>`` fetches that registered version instead, whose kind
            and action space (and, for ``carp_msvq``, ``scales`` and ``codebook_size``) must match these params.
        tasks: Tasks whose demo windows train the tokenizer, each normalized with its own min-max statistics; empty
            means the pipeline's ``tasks``. Every entry must also be in ``tasks`` (its demos are ingested there).
        latent_channels: ``C``, latent channels per action dimension, which is also the width of a code; an integer
            >= 1.
        base_channels: Channels per action dimension of the encoder's first convolution; an integer >= 1. Level i of
            the encoder has ``base_channels * channel_mult[i]`` channels per dimension.
        channel_mult: Channel multiplier of each encoder level (the decoder mirrors it); a non-empty list of positive
            integers. Each level halves the time length, so the encoder's output is ``action_horizon /
            2**len(channel_mult)`` steps long; ``scales`` may end below or above that length (the latent length ``l``
            in docs/architecture.md, "Symbols").
        commitment_weight: Weight of the commitment loss that pulls encoder latents towards their quantized values,
            relative to the reconstruction loss; a number >= 0.
        epochs: Passes over the training windows; an integer >= 1.
        batch_size: Windows per optimizer step; an integer >= 1.
        learning_rate: Peak AdamW learning rate, reached after a linear warm-up and followed by a cosine decay to 5% of
            the peak; a number > 0.
        weight_decay: AdamW weight decay of the convolution weights (biases, norms and the codebook are not decayed);
            a number >= 0.
        checkpoint_every: Epochs between resumable training states in ``checkpoints/``; an integer >= 1. The last
            epoch is always saved.
        seed: Seeds weight initialization, shuffling, augmentation and code restarts; any integer.
        registry_alias: Alias the ``register_tokenizer`` stage sets on the registered version: letters, digits,
            ``_`` and ``-``, not ``latest``, not ``v<digits>`` and not starting with a digit (reserved by the MLflow
            registry).
        warmup_fraction: Share of the optimizer steps with a linear learning-rate warm-up; a number in [0, 1].
        restart_fraction: Share of the epochs, from the first, after which codes no training token used in that
            epoch are re-seeded from the data; a number in [0, 1].
        augment_probability: Chance, per training window, action dimension and epoch, that the window's values in
            that dimension are rescaled and moved inside [-1, 1]; a number in [0, 1] (0 turns augmentation off).
        augment_max_scale: Largest amplitude factor of that augmentation (``1 / augment_max_scale`` is the smallest,
            1 only moves); a number >= 1.
    """

    kind: str = DEFAULT_TOKENIZER_KIND

    source: str = "pipeline"
    tasks: tuple[str, ...] = ()
    latent_channels: int = 8
    base_channels: int = 2
    channel_mult: tuple[int, ...] = (2, 4)
    commitment_weight: float = 0.25
    epochs: int = 60
    batch_size: int = 64
    learning_rate: float = 1e-2
    weight_decay: float = 0.0
    checkpoint_every: int = 5
    seed: int = 0
    registry_alias: str = "default"
    warmup_fraction: float = 0.05
    restart_fraction: float = 0.25
    augment_probability: float = 0.5
    augment_max_scale: float = 2.0

    def __post_init__(self) -> None:
        _require(
            self.kind in TOKENIZER_KINDS, "tokenizer.kind", self.kind, f"must be one of {', '.join(TOKENIZER_KINDS)}"
        )
        _require(
            self.source == "pipeline" or (self.source.startswith(REGISTRY_URI_PREFIX) and "@" in self.source),
            "tokenizer.source",
            self.source,
            "must be 'pipeline' or a registry URI 'models:/<name>@<alias>'",
        )
        _require(self.latent_channels >= 1, "tokenizer.latent_channels", self.latent_channels, "must be >= 1")
        _require(self.base_channels >= 1, "tokenizer.base_channels", self.base_channels, "must be >= 1")
        _require(
            len(self.channel_mult) >= 1 and all(m >= 1 for m in self.channel_mult),
            "tokenizer.channel_mult",
            self.channel_mult,
            "must be a non-empty list of positive integers",
        )
        _require(self.commitment_weight >= 0, "tokenizer.commitment_weight", self.commitment_weight, "must be >= 0")
        _positive_training_fields(self, "tokenizer")
        require_registry_alias("tokenizer.registry_alias", self.registry_alias)
        for name in ("warmup_fraction", "restart_fraction", "augment_probability"):
            _require(0.0 <= getattr(self, name) <= 1.0, f"tokenizer.{name}", getattr(self, name), "must be in [0, 1]")
        _require(self.augment_max_scale >= 1.0, "tokenizer.augment_max_scale", self.augment_max_scale, "must be >= 1")
