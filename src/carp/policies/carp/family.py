"""CARP's entry in the policy registry (`carp.policies.registry`): its config, builder, loader and trainer."""

from carp.policies.carp.config import CarpConfig, CarpInference
from carp.policies.carp.policy import CarpPolicy
from carp.policies.carp.spec import PolicySpec
from carp.policies.carp.trainer import train_carp
from carp.policies.carp.transformer import CoarseToFineTransformer
from carp.policies.context import PolicyContext
from carp.policies.policy_family import PolicyFamily
from carp.training.run import TrainingRun
from carp.training.runtime import seed_everything


def policy_spec(config: CarpConfig, context: PolicyContext) -> PolicySpec:
    """The transformer's spec: `config` with the shapes of the data and the tokenizer of `context`.

    Raises:
        ValueError: `context` has no tokenizer (CARP predicts its tokens).
    """
    if context.tokenizer_artifact is None:
        raise ValueError("a carp policy needs the registered tokenizer")
    tokenizer_spec = context.tokenizer_artifact.tokenizer.spec
    return PolicySpec(
        obs_dim=context.feature_dim,
        obs_steps=context.obs_steps,
        action_dim=context.action_dim,
        scales=tokenizer_spec.scales,
        latent_channels=tokenizer_spec.latent_channels,
        codebook_size=tokenizer_spec.codebook_size,
        config=config,
    )


def build_policy(config: CarpConfig, context: PolicyContext) -> CarpPolicy:
    """An untrained CARP policy sized by `config` for the data and tokenizer of `context`."""
    return CarpPolicy(
        context.tokenizer_artifact,
        CoarseToFineTransformer(policy_spec(config, context)),
        context.obs_normalizer,
        context.action_normalizer,
        context.metadata,
        context.image_encoder,
    )


def train(config: CarpConfig, run: TrainingRun) -> CarpPolicy:
    """Build the policy after seeding (reproducible weights) and train its transformer in the shared loop."""
    seed_everything(run.training.seed)
    return train_carp(build_policy(config, run.context), config, run)


FAMILY = PolicyFamily("carp", CarpConfig, CarpInference, build_policy, CarpPolicy.from_checkpoint, train)
