"""The two Diffusion Policy entries of the policy registry: DP-C (`diffusion_unet`) and DP-T (`diffusion_transformer`).

Both train through the shared loop (`carp.training.loop`) on DP's noise-regression loss, with DP's optimizer recipe:
AdamW with betas (0.95, 0.999), linear warm-up then cosine decay, and DP's EMA of the weights with its warm-up
(`carp.policies.diffusion.ema`). DP-T forms its parameter groups as DP does (no decay on biases, norms and position
embeddings).
"""

import dataclasses
import functools

from carp.policies.context import PolicyContext
from carp.policies.diffusion.config import (
    DenoisingConfig,
    DiffusionTransformerConfig,
    DiffusionTransformerSampling,
    DiffusionUNetConfig,
    DiffusionUNetSampling,
)
from carp.policies.diffusion.ema import exponential_moving_average
from carp.policies.diffusion.policy import DenoiserFactory, DiffusionPolicy, from_checkpoint
from carp.policies.diffusion.transformer import DiffusionTransformer
from carp.policies.diffusion.unet import ConditionalUNet1D
from carp.policies.policy_family import PolicyFamily
from carp.training.loop import OptimizerRecipe
from carp.training.run import TrainingRun
from carp.training.runtime import seed_everything

ADAM_BETAS = (0.95, 0.999)
"""DP's AdamW betas (its lowdim workspace configs)."""


def make_unet(config: DiffusionUNetConfig, action_dim: int, obs_dim: int, obs_steps: int, action_horizon: int):
    """DP-C's denoiser; the U-Net does not depend on the horizon (only its divisibility, checked per call)."""
    return ConditionalUNet1D(config, action_dim, obs_dim, obs_steps)


def make_transformer(
    config: DiffusionTransformerConfig, action_dim: int, obs_dim: int, obs_steps: int, action_horizon: int
):
    """DP-T's denoiser, with one position embedding row per action of the horizon."""
    return DiffusionTransformer(config, action_dim, obs_dim, obs_steps, action_horizon)


def build(policy_type: str, make_denoiser: DenoiserFactory, config: DenoisingConfig, context: PolicyContext):
    """An untrained policy of `policy_type` sized for the data of `context` (the tokenizer is not used)."""
    denoiser = make_denoiser(config, context.action_dim, context.feature_dim, context.obs_steps, context.action_horizon)
    return DiffusionPolicy(
        policy_type,
        config,
        denoiser,
        context.obs_normalizer,
        context.action_normalizer,
        context.action_horizon,
        context.metadata,
        context.image_encoder,
    )


def train(
    policy_type: str, make_denoiser: DenoiserFactory, config: DenoisingConfig, run: TrainingRun
) -> DiffusionPolicy:
    """Build the policy after seeding (reproducible weights) and train it on DP's loss in the shared loop."""
    seed_everything(run.training.seed)
    policy = build(policy_type, make_denoiser, config, run.context)
    ema = None
    if config.use_ema:
        ema = functools.partial(exponential_moving_average, power=config.ema_power, max_decay=config.ema_max_decay)
    groups = getattr(policy.denoiser, "parameter_groups", None)
    recipe = OptimizerRecipe(
        learning_rate=config.learning_rate,
        weight_decay=config.weight_decay,
        warmup_steps=config.warmup_steps,
        betas=ADAM_BETAS,
        ema=ema,
        parameter_groups=(lambda: groups(config.weight_decay)) if groups is not None else None,
    )
    identity = {"policy_type": policy_type, "config": dataclasses.asdict(config), "shapes": _shapes(run.context)}
    return run.train_with_loss(policy, recipe, identity)


def _shapes(context: PolicyContext) -> dict[str, int]:
    return {
        "obs_dim": context.feature_dim,
        "obs_steps": context.obs_steps,
        "action_dim": context.action_dim,
        "action_horizon": context.action_horizon,
    }


def _family(name: str, config_class: type, inference_class: type, make_denoiser: DenoiserFactory) -> PolicyFamily:
    return PolicyFamily(
        name,
        config_class,
        inference_class,
        functools.partial(build, name, make_denoiser),
        functools.partial(from_checkpoint, policy_type=name, config_class=config_class, make_denoiser=make_denoiser),
        functools.partial(train, name, make_denoiser),
    )


UNET_FAMILY = _family("diffusion_unet", DiffusionUNetConfig, DiffusionUNetSampling, make_unet)
TRANSFORMER_FAMILY = _family(
    "diffusion_transformer", DiffusionTransformerConfig, DiffusionTransformerSampling, make_transformer
)
