"""The VQ-BeT entry of the policy registry, and its two-phase training.

Phase 1 fits the action VQ-VAE (`carp.tokenizer.kinds.chunk_vqvae`) on the training chunks, deterministic given the
seed, and keeps it in the run's checkpoint directory (`action_vqvae.pt`, with what it was trained from): a resumed
or repeated run of the same setup loads it instead of refitting. Phase 2 trains the GPT and its heads against the
frozen VQ-VAE's codes in the shared resumable loop (`carp.training.loop`), with VQ-BeT's AdamW (betas 0.9, 0.95; no
decay on biases, norms and the position embedding) and its schedule: after `freeze_fraction` of the epochs the GPT
and the code head stop and only the offset head trains (`VqBetPolicy.training_loss`).
"""

import dataclasses
import logging
import math
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from carp.policies.context import PolicyContext
from carp.policies.policy_family import PolicyFamily
from carp.policies.vq_bet.config import VqBetConfig, VqBetInference
from carp.policies.vq_bet.policy import POLICY_TYPE, VqBetPolicy, autoencoder_shape
from carp.policies.vq_bet.transformer import BehaviorTransformer
from carp.tokenizer.kinds.chunk_vqvae import ActionAutoencoder, AutoencoderTraining, train_autoencoder
from carp.training import distributed
from carp.training.checkpoint import CheckpointError, atomic_torch_save, read_checkpoint
from carp.training.loop import OptimizerRecipe, data_digest, matrix_decay_groups
from carp.training.run import TrainingRun
from carp.training.runtime import resolve_device, seed_everything

logger = logging.getLogger(__name__)

ADAM_BETAS = (0.9, 0.95)
AUTOENCODER_NAME = "action_vqvae.pt"
"""The fitted VQ-VAE in the run's checkpoint directory."""


def build(config: VqBetConfig, context: PolicyContext) -> VqBetPolicy:
    """An untrained VQ-BeT policy (VQ-VAE included) sized by `config` for the data of `context`."""
    transformer = BehaviorTransformer(
        config, context.feature_dim, context.obs_steps, context.action_horizon, context.action_dim
    )
    autoencoder = ActionAutoencoder(autoencoder_shape(config, context.action_horizon, context.action_dim))
    return VqBetPolicy(
        autoencoder,
        transformer,
        context.obs_normalizer,
        context.action_normalizer,
        context.metadata,
        context.image_encoder,
    )


def autoencoder_training(config: VqBetConfig, seed: int) -> AutoencoderTraining:
    """The VQ-VAE phase's settings from `config`, seeded with the run's seed."""
    return AutoencoderTraining(
        config.vq_training_steps,
        config.vq_batch_size,
        config.vq_learning_rate,
        config.vq_weight_decay,
        config.commitment_weight,
        seed,
    )


def fit_autoencoder(autoencoder: ActionAutoencoder, run: TrainingRun, training: AutoencoderTraining) -> dict[str, Any]:
    """Fit the VQ-VAE on the run's chunks, or load the one a run of the same setup left; returns its identity.

    The identity (sizes, training settings, sha256 of the windows) is stored with the weights; a file of another
    identity, or one that cannot be read, is refitted and overwritten with a warning.
    """
    identity = {
        "shape": dataclasses.asdict(autoencoder.shape),
        "training": dataclasses.asdict(training),
        "data_sha256": data_digest(run.data),
    }
    path = Path(run.checkpoint_dir) / AUTOENCODER_NAME
    if path.is_file():
        try:
            stored = read_checkpoint(path, weights_only=True)
            if stored.get("identity") == identity:
                autoencoder.load_state_dict(stored["state"], strict=True)
                autoencoder.eval().requires_grad_(False)
                logger.info("vq_bet: reusing the fitted VQ-VAE in %s", path)
                return identity
            logger.warning("%s was fitted for another setup; refitting the VQ-VAE", path)
        except (CheckpointError, KeyError, RuntimeError, AttributeError) as error:
            logger.warning("%s cannot be used (%s); refitting the VQ-VAE", path, error)
    device = resolve_device(str(run.device))
    # float32 whatever the loop's precision: the VQ-VAE phase runs outside its autocast.
    train_autoencoder(autoencoder.to(device), run.data.actions.to(device=device, dtype=torch.float32), training)
    autoencoder.to("cpu")
    atomic_torch_save({"identity": identity, "state": autoencoder.state_dict()}, path)
    return identity


def train(config: VqBetConfig, run: TrainingRun) -> VqBetPolicy:
    """Build the policy after seeding, fit (or reload) its VQ-VAE, then train the GPT and heads in the shared loop."""
    seed_everything(run.training.seed)
    context = run.context
    policy = build(config, context)
    vq_training = autoencoder_training(config, run.training.seed)
    # Under several processes rank 0 fits and saves the VQ-VAE and the others load it: one set of codes for all.
    vq_identity = distributed.main_process_first(
        lambda: fit_autoencoder(policy.autoencoder, run, vq_training), distributed.current_processes()
    )
    epochs = run.training.epochs if run.epochs is None else run.epochs
    steps_per_epoch = math.ceil(run.data.obs.shape[0] / run.training.batch_size)
    policy.freeze_after_steps = math.ceil(epochs * config.freeze_fraction) * steps_per_epoch

    def average(module: nn.Module) -> AveragedModel:
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
        "shapes": {
            "obs_dim": context.feature_dim,
            "obs_steps": context.obs_steps,
            "action_horizon": context.action_horizon,
            "action_dim": context.action_dim,
        },
        "autoencoder": vq_identity,
    }
    return run.train_with_loss(policy, recipe, identity)


FAMILY = PolicyFamily(POLICY_TYPE, VqBetConfig, VqBetInference, build, VqBetPolicy.from_checkpoint, train)
