"""Config of the next-token autoregressive family: one frozen dataclass, validated at construction.

It is the family's params section (`next_token`) and what its checkpoint stores; the token choice at evaluation is
the separate section `inference.next_token` (:class:`NextTokenInference`). The transformer's defaults are CARP's
(`carp.policies.carp.config.TransformerConfig`), so that the two families differ only in how many tokens a step
predicts.
Shapes that come from the data and the tokenizer (`Do`, `To`, `A`, scales, `V`) are passed to the model separately;
loop settings shared by every family (epochs, batch size, checkpoints, seed) are the `training` section.
"""

from dataclasses import dataclass
from typing import ClassVar

from carp.config.checks import require_bool
from carp.config.tokenizer_kinds import TOKENIZER_KINDS
from carp.policies.carp.config import CarpInference, TransformerConfig

SECTION = "next_token"


@dataclass(frozen=True)
class NextTokenConfig(TransformerConfig):
    """The next-token transformer (`carp.policies.next_token.transformer`) and its optimizer.

    Its fields, defaults, constraints and descriptions are those CARP's section shares
    (:class:`~carp.policies.carp.config.TransformerConfig`), plus one of its own.

    Attributes:
        match_size: Over a tokenizer kind other than carp_msvq, replace ``width`` by the multiple of ``num_heads``
            whose transformer has the trained parameters nearest those the section's transformer has over carp_msvq's
            tokens at ``width`` (the params' ``scales`` and ``codebook_size``), so that kinds compare at one network
            size (`carp.policies.next_token.matched_size`); the checkpoint records the width chosen. Over carp_msvq it
            changes nothing. true or false.
    """

    match_size: bool = True

    SECTION: ClassVar[str] = SECTION
    TOKENIZER_KINDS: ClassVar[tuple[str, ...]] = TOKENIZER_KINDS
    """Every kind: the family predicts any kind's token sequence (`carp.policies.next_token.kind_policy`)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        require_bool(f"{self.SECTION}.match_size", self.match_size)


@dataclass(frozen=True)
class NextTokenInference(CarpInference):
    """How evaluation chooses the next-token policy's tokens; decoding only, so a change reruns evaluation.

    Its fields and constraints are CARP's (:class:`~carp.policies.carp.config.CarpInference`).
    """

    SECTION: ClassVar[str] = SECTION


SECTIONS = (NextTokenConfig, NextTokenInference)
"""The registry's view of this module: the `next_token` and `inference.next_token` sections."""
