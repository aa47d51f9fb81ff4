"""The two Consistency Policy entries of the policy registry: EDM teacher `edm_unet`, student `consistency_policy`.

Both train in the shared loop (`carp.training.loop`) with DP's optimizer recipe (AdamW, betas 0.95 and 0.999, linear
warm-up then cosine decay) and DP's EMA of the weights for evaluation. The student declares its teacher family: its
training is given the trained teacher (`TrainingRun.teacher`), starts from the teacher's weights and distils it
(`carp.policies.consistency.distillation`), with a digest of the teacher's weights in the run's identity so that a
resumed run never mixes two teachers.
"""

import dataclasses
import functools
import hashlib

import torch

from carp.policies.consistency.config import (
    STUDENT,
    TEACHER,
    UNET_FIELDS,
    ConsistencyConfig,
    ConsistencySampling,
    EDMConfig,
    EDMSampling,
)
from carp.policies.consistency.distillation import Distillation, warm_start
from carp.policies.consistency.karras import KarrasSchedule
from carp.policies.consistency.policy import ConsistencyPolicy, EDMPolicy, KarrasPolicy, schedule_of
from carp.policies.context import PolicyContext
from carp.policies.diffusion.ema import exponential_moving_average
from carp.policies.diffusion.unet import ConditionalUNet1D
from carp.policies.policy_family import PolicyFamily
from carp.training.loop import OptimizerRecipe, TrainingStep
from carp.training.run import TrainingRun
from carp.training.runtime import seed_everything

ADAM_BETAS = (0.95, 0.999)
"""DP's AdamW betas, which the official Consistency Policy configs keep."""


def _build(policy_class: type[KarrasPolicy], config, context: PolicyContext, schedule: KarrasSchedule) -> KarrasPolicy:
    if context.num_tasks > 0:
        raise ValueError(f"a {policy_class.policy_type} policy is single-task; got num_tasks = {context.num_tasks}")
    unet = ConditionalUNet1D(
        config, context.action_dim, context.feature_dim, context.obs_steps, policy_class.num_noise_inputs
    )
    return policy_class(
        config,
        unet,
        schedule,
        context.obs_normalizer,
        context.action_normalizer,
        context.action_horizon,
        context.metadata,
        context.image_encoder,
    )


def build_teacher(config: EDMConfig, context: PolicyContext) -> EDMPolicy:
    """An untrained EDM teacher sized by `config` for the data of `context`."""
    return _build(EDMPolicy, config, context, schedule_of(config))


def build_student(config: ConsistencyConfig, context: PolicyContext) -> ConsistencyPolicy:
    """An untrained student sized by `config`, with the default teacher's noise schedule.

    Training replaces the schedule by its teacher's.
    """
    return _build(ConsistencyPolicy, config, context, schedule_of(EDMConfig()))


def _recipe(config) -> OptimizerRecipe:
    ema = None
    if config.use_ema:
        ema = functools.partial(exponential_moving_average, power=config.ema_power, max_decay=config.ema_max_decay)
    return OptimizerRecipe(
        learning_rate=config.learning_rate,
        weight_decay=config.weight_decay,
        warmup_steps=config.warmup_steps,
        betas=ADAM_BETAS,
        ema=ema,
    )


def _shapes(context: PolicyContext) -> dict[str, int]:
    return {
        "obs_dim": context.feature_dim,
        "obs_steps": context.obs_steps,
        "action_dim": context.action_dim,
        "action_horizon": context.action_horizon,
    }


def train_teacher(config: EDMConfig, run: TrainingRun) -> EDMPolicy:
    """Build the teacher after seeding and train it on EDM's loss in the shared loop."""
    seed_everything(run.training.seed)
    policy = build_teacher(config, run.context)
    identity = {"policy_type": TEACHER, "config": dataclasses.asdict(config), "shapes": _shapes(run.context)}
    return run.train_with_loss(policy, _recipe(config), identity)


def check_teacher(teacher: object, config: ConsistencyConfig, context: PolicyContext) -> EDMPolicy:
    """`teacher`, checked against the student's config and the data's shapes.

    Raises:
        ValueError: not an EDM teacher, or a U-Net or shapes that differ from the student's.
    """
    if not isinstance(teacher, EDMPolicy):
        raise ValueError(f"the teacher must be an {TEACHER} policy, got {getattr(teacher, 'policy_type', teacher)}")
    for name in UNET_FIELDS:
        ours, theirs = getattr(config, name), getattr(teacher.config, name)
        if ours != theirs:
            raise ValueError(f"the teacher's {TEACHER}.{name}={theirs} differs from {STUDENT}.{name}={ours}")
    shapes = teacher.family_checkpoint()["shapes"]
    if shapes != _shapes(context):
        raise ValueError(f"the teacher was trained for shapes {shapes}, the data has {_shapes(context)}")
    return teacher


def weights_digest(module: torch.nn.Module) -> str:
    """sha256 over the names and bytes of `module`'s state (its weights and buffers), on the CPU."""
    digest = hashlib.sha256()
    for name, value in module.state_dict().items():
        digest.update(name.encode())
        digest.update(value.detach().cpu().contiguous().view(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def train_student(config: ConsistencyConfig, run: TrainingRun) -> ConsistencyPolicy:
    """Warm-start the student from its trained teacher and distil the teacher in the shared loop.

    Raises:
        ValueError: the run has no teacher, or one that does not fit (see :func:`check_teacher`).
    """
    if run.teacher is None:
        raise ValueError(f"a {STUDENT} policy distils an {TEACHER} teacher; the run has no teacher")
    teacher = check_teacher(run.teacher, config, run.context)
    seed_everything(run.training.seed)
    policy = _build(ConsistencyPolicy, config, run.context, teacher.schedule)
    warm_start(policy.unet, teacher.unet)
    # The teacher's observation encoder (camera features of an image policy), kept frozen as the official student
    # keeps it: the teacher and the student then read the same features.
    policy.observation_encoder.load_state_dict(teacher.observation_encoder.state_dict())
    policy.observation_encoder.requires_grad_(False)
    policy.distillation = Distillation(
        teacher.unet,
        policy.unet,
        teacher.schedule,
        config.num_levels,
        config.teacher_steps,
        config.target_decay,
        teacher.config.log_sigma_mean,
        teacher.config.log_sigma_std,
    )

    def training_step(batch) -> TrainingStep:
        losses = policy.distillation(policy, batch)
        loss = losses.total(config.trajectory_weight, config.denoising_weight)
        count = batch["actions"].shape[0]
        # Batch means times the batch size: the loop reports them as epoch means.
        metric_sums = {
            "trajectory_loss": losses.trajectory.detach() * count,
            "denoising_loss": losses.denoising.detach() * count,
            "denoising_scale": losses.denoising_scale * count,
        }
        return TrainingStep(loss, metric_sums)

    identity = {
        "policy_type": STUDENT,
        "config": dataclasses.asdict(config),
        "shapes": _shapes(run.context),
        "teacher_sha256": weights_digest(teacher),
    }
    trained = run.train_with_loss(policy, _recipe(config), identity, training_step=training_step)
    trained.distillation = None
    # Frozen for the distillation only: the trained policy counts and loads its encoder like any other.
    trained.observation_encoder.requires_grad_(True)
    return trained


TEACHER_FAMILY = PolicyFamily(TEACHER, EDMConfig, EDMSampling, build_teacher, EDMPolicy.from_checkpoint, train_teacher)
STUDENT_FAMILY = PolicyFamily(
    STUDENT,
    ConsistencyConfig,
    ConsistencySampling,
    build_student,
    ConsistencyPolicy.from_checkpoint,
    train_student,
)
