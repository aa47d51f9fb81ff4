"""CARP's entry in the policy registry (`carp.policies.registry`): its config, builder, loader and trainer."""

from carp.policies.carp.config import CarpConfig, CarpInference
from carp.policies.carp.policy import CarpPolicy
from carp.policies.carp.spec import PolicySpec
from carp.policies.carp.trainer import train_policy
from carp.policies.carp.transformer import CoarseToFineTransformer
from carp.policies.context import PolicyContext
from carp.policies.registry import PolicyFamily, TrainingRun


def policy_spec(config: CarpConfig, context: PolicyContext) -> PolicySpec:
    """The transformer's spec: `config`'s architecture, sized for the data and the tokenizer of `context`.

    Raises:
        ValueError: `context` has no tokenizer (CARP predicts its tokens).
    """
    if context.tokenizer_artifact is None:
        raise ValueError("a carp policy needs the registered tokenizer")
    tokenizer_spec = context.tokenizer_artifact.tokenizer.spec
    return PolicySpec(
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


def build_policy(config: CarpConfig, context: PolicyContext) -> CarpPolicy:
    """An untrained CARP policy sized by `config` for the data and tokenizer of `context`."""
    return CarpPolicy(
        context.tokenizer_artifact,
        CoarseToFineTransformer(policy_spec(config, context)),
        context.obs_normalizer,
        context.action_normalizer,
        context.metadata,
    )


def train(config: CarpConfig, run: TrainingRun) -> CarpPolicy:
    """Train CARP's transformer on the frozen tokenizer's tokens (`carp.policies.carp.trainer`) and assemble it."""
    context = run.context
    spec = policy_spec(config, context)
    tokenizer = context.tokenizer_artifact.tokenizer
    transformer = train_policy(
        spec,
        tokenizer,
        run.data,
        config,
        run.training,
        run.checkpoint_dir,
        run.on_epoch_end,
        epochs=run.epochs,
        device=run.device,
    )
    tokenizer.cpu()
    return CarpPolicy(
        context.tokenizer_artifact,
        transformer.cpu(),
        context.obs_normalizer,
        context.action_normalizer,
        context.metadata,
    ).eval()


FAMILY = PolicyFamily("carp", CarpConfig, CarpInference, build_policy, CarpPolicy.from_checkpoint, train)
