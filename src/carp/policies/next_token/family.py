"""The next-token entry of the policy registry: the registered tokenizer's tokens, one per step, at CARP's size.

With carp_msvq (the default kind) it predicts CARP's tokens in CARP's order (`policy`); with any other kind, that
kind's tokens over its own vocabulary (`kind_policy`).

It trains through the shared loop (`carp.training.loop`) on teacher-forced cross entropy with CARP's optimizer recipe
(AdamW betas 0.9/0.95 as in VAR, no weight decay on biases and embeddings, linear warm-up then cosine decay, optional
EMA with a constant decay), so that the two families differ in how many tokens a step predicts and nothing else.
"""

import dataclasses
import logging
from typing import Any

from torch import nn
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from carp.policies.context import PolicyContext
from carp.policies.next_token.config import NextTokenConfig, NextTokenInference
from carp.policies.next_token.kind_policy import TOKENIZER_KEY, NextTokenKindPolicy
from carp.policies.next_token.matched_size import msvq_parameters, width_nearest
from carp.policies.next_token.policy import POLICY_TYPE, NextTokenPolicy
from carp.policies.next_token.transformer import NextTokenTransformer
from carp.policies.policy_family import PolicyFamily
from carp.tokenizer.kinds.artifact import KindArtifact
from carp.training.loop import OptimizerRecipe, matrix_decay_groups
from carp.training.run import TrainingRun
from carp.training.runtime import seed_everything

ADAM_BETAS = (0.9, 0.95)
logger = logging.getLogger(__name__)


def build(config: NextTokenConfig, context: PolicyContext) -> NextTokenPolicy | NextTokenKindPolicy:
    """An untrained next-token policy sized by `config` for the data and tokenizer of `context`.

    carp_msvq's artifact gives :class:`NextTokenPolicy` (per-dimension vocabularies, CARP's token order); any other
    kind's gives :class:`NextTokenKindPolicy` (one shared vocabulary, an end token for a variable-length kind), at
    the width that matches carp_msvq's size when `config.match_size` (`carp.policies.next_token.matched_size`).

    Raises:
        ValueError: no tokenizer in the context, or a size to match without the context's `msvq_layout`.
    """
    if context.tokenizer_artifact is None:
        raise ValueError("a next_token policy needs the registered tokenizer")
    if isinstance(context.tokenizer_artifact, KindArtifact):
        tokenizer = context.tokenizer_artifact.tokenizer

        def kind_transformer(sized: NextTokenConfig) -> NextTokenTransformer:
            return NextTokenKindPolicy.transformer_for(sized, context.feature_dim, context.obs_steps, tokenizer)

        if config.match_size:
            if context.msvq_layout is None:
                raise ValueError(
                    "next_token.match_size needs the params' scales and codebook_size (the context's msvq_layout)"
                )
            target = msvq_parameters(
                config, context.feature_dim, context.obs_steps, context.action_dim, context.msvq_layout
            )
            width = config.width
            config, matched = width_nearest(config, target, kind_transformer)
            logger.info(
                "next_token over %s at width %d: %d trained parameters, %.2f x its %d over carp_msvq at width %d",
                tokenizer.kind,
                config.width,
                matched,
                matched / target,
                target,
                width,
            )
        return NextTokenKindPolicy(
            context.tokenizer_artifact,
            kind_transformer(config),
            context.obs_normalizer,
            context.action_normalizer,
            context.metadata,
            context.image_encoder,
        )
    spec = context.tokenizer_artifact.tokenizer.spec
    transformer = NextTokenTransformer(
        config,
        context.feature_dim,
        context.obs_steps,
        context.action_dim,
        tuple(spec.scales),
        spec.codebook_size,
    )
    return NextTokenPolicy(
        context.tokenizer_artifact,
        transformer,
        context.obs_normalizer,
        context.action_normalizer,
        context.metadata,
        context.image_encoder,
    )


def from_checkpoint(checkpoint: dict[str, Any]) -> NextTokenPolicy | NextTokenKindPolicy:
    """Rebuild either next-token policy: one that embeds another kind's files (`tokenizer_kind`) or carp_msvq's."""
    if TOKENIZER_KEY in checkpoint:
        return NextTokenKindPolicy.from_checkpoint(checkpoint)
    return NextTokenPolicy.from_checkpoint(checkpoint)


def train(config: NextTokenConfig, run: TrainingRun) -> NextTokenPolicy | NextTokenKindPolicy:
    """Build the policy after seeding (reproducible weights) and train it in the shared loop."""
    seed_everything(run.training.seed)
    context = run.context
    policy = build(config, context)

    def average(module: nn.Module) -> AveragedModel:
        # Parameters only: the buffers are constant index tables and masks.
        return AveragedModel(module, multi_avg_fn=get_ema_multi_avg_fn(config.ema_decay), use_buffers=False)

    recipe = OptimizerRecipe(
        learning_rate=config.learning_rate,
        weight_decay=config.weight_decay,
        warmup_steps=config.warmup_steps,
        betas=ADAM_BETAS,
        ema=average if config.use_ema else None,
        parameter_groups=lambda: matrix_decay_groups(policy.transformer, config.weight_decay),
    )
    identity = {
        "policy_type": POLICY_TYPE,
        "config": dataclasses.asdict(config),
        "shapes": {"obs_dim": context.feature_dim, "obs_steps": context.obs_steps, "action_dim": context.action_dim},
        "tokenizer_sha256": context.tokenizer_artifact.sha256,
    }
    return run.train_with_loss(policy, recipe, identity)


FAMILY = PolicyFamily(POLICY_TYPE, NextTokenConfig, NextTokenInference, build, from_checkpoint, train)
