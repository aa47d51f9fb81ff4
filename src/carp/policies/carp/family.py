"""CARP's entry in the policy registry (`carp.policies.registry`): its config, builder and loader."""

from carp.config import PolicyConfig
from carp.policies.carp.policy import CarpPolicy
from carp.policies.carp.spec import PolicySpec
from carp.policies.carp.transformer import CoarseToFineTransformer
from carp.policies.context import PolicyContext
from carp.policies.registry import PolicyFamily


def build_policy(config: PolicyConfig, context: PolicyContext) -> CarpPolicy:
    """An untrained CARP policy sized by `config` for the data and tokenizer of `context`.

    Raises:
        ValueError: `context` has no tokenizer (CARP predicts its tokens).
    """
    if context.tokenizer_artifact is None:
        raise ValueError("a carp policy needs the registered tokenizer")
    tokenizer_spec = context.tokenizer_artifact.tokenizer.spec
    spec = PolicySpec(
        obs_dim=context.obs_dim,
        obs_steps=context.obs_steps,
        action_dim=context.action_dim,
        scales=tokenizer_spec.scales,
        latent_channels=tokenizer_spec.latent_channels,
        codebook_size=tokenizer_spec.codebook_size,
        num_tasks=context.num_tasks,
        depth=config.depth,
        width=config.width,
        num_heads=config.num_heads,
        mlp_ratio=config.mlp_ratio,
        dropout=config.dropout,
    )
    return CarpPolicy(
        context.tokenizer_artifact,
        CoarseToFineTransformer(spec),
        context.obs_normalizer,
        context.action_normalizer,
        context.metadata,
    )


FAMILY = PolicyFamily("carp", PolicyConfig, build_policy, CarpPolicy.from_checkpoint)
