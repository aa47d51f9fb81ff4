"""Consistency-trajectory distillation of the EDM teacher into the student, and the student's warm start.

Follows Consistency Trajectory Models (Kim et al., ICLR 2024) as Consistency Policy's official code applies it
(`consistency_policy/student/ctm_policy.py`, `compute_loss`), with its defaults. Per sample, three positions of the
N-level discretization are drawn: the start t uniform in [0, N - 1], the target s uniform in [t, N] (N stands for
sigma_min), the middle u uniform in [t, s] and at most `teacher_steps` past t. The clean chunk is noised to level t;
the teacher's Heun steps carry it to level u. The loss compares the student's jump t -> s with the target network's
jump u -> s, both carried on to sigma_min by the target network:

    trajectory = d(G_target(G(x_t, t, s), s, sigma_min), G_target(G_target(x_u, u, s), s, sigma_min))

with d the pseudo-Huber error of `carp.policies.consistency.karras`. The denoising loss asks the student's denoiser
g(x_sigma, sigma, sigma) to return the clean chunk, at levels drawn half from the upper 70% of the discretization
(in rho-space) and half log-normally, weighted by EDM's lambda(sigma). The denoising loss enters the total scaled
by CTM's adaptive weight (`adaptive_scale`): the ratio of the two losses' gradient norms at the U-Net's output
layer, so that `denoising_weight` is relative to the trajectory loss's pull. Unscaled, the denoising loss is orders
of magnitude larger than the trajectory loss and pulls the one-step jump to the posterior mean, between the modes
of a multimodal chunk distribution.

Deviations from the official code, all three as in CTM's paper: the gradient flows through the target network's
jump s -> sigma_min into the student's output (the official code runs that jump without gradient, which leaves the
trajectory loss without effect); the denoising loss reads g at target level sigma (the official code reads the jump
to sigma_min, whose regression to the posterior mean at high noise levels undoes the one-step jump to a mode); the
adaptive weight above (the official code weights the two losses by fixed constants).

The warm start copies the teacher's U-Net into the student, whose FiLM projections read one more step embedding
(the target level): its columns start at zero, so the warm-started student's jump to any level is the teacher's
denoiser mixed by s / t, as in the official warm start.
"""

from typing import NamedTuple

import torch
from torch import nn

from carp.policies.consistency.karras import KarrasSchedule, expand_like, heun_step, pseudo_huber
from carp.policies.diffusion.unet import ConditionalUNet1D

DENOISING_RHO_SPAN = 0.7
"""The denoising loss's first half draws its levels from this upper share of the discretization (in rho-space)."""


ADAPTIVE_EPSILON = 1e-4
"""Added to the denoising gradient's norm in the adaptive weight (CTM's constant), against division by zero."""

ADAPTIVE_MAX = 1e4
"""Cap of the adaptive weight (CTM's), for a denoising gradient that vanishes."""


class DistillationLosses(NamedTuple):
    """The two losses of one batch and the denoising loss's adaptive scale (scalars; the scale without gradient)."""

    trajectory: torch.Tensor
    denoising: torch.Tensor
    denoising_scale: torch.Tensor

    def total(self, trajectory_weight: float, denoising_weight: float) -> torch.Tensor:
        """trajectory_weight * trajectory + denoising_weight * denoising_scale * denoising (scalar)."""
        return trajectory_weight * self.trajectory + denoising_weight * self.denoising_scale * self.denoising


def adaptive_scale(trajectory: torch.Tensor, denoising: torch.Tensor, layer: torch.Tensor) -> torch.Tensor:
    """CTM's adaptive weight of the denoising loss: the ratio of the two losses' gradient norms at `layer`.

    Scaled by it, the denoising loss moves the network's last layer as strongly as the trajectory loss does,
    whatever the two losses' magnitudes (the denoising loss's is orders larger at the start of distillation).

    Args:
        trajectory: the trajectory loss (scalar, with gradient).
        denoising: the denoising loss (scalar, with gradient).
        layer: a parameter both losses reach (the U-Net's output projection).

    Returns:
        The weight (scalar, without gradient), in [0, ADAPTIVE_MAX].
    """
    if not (trajectory.requires_grad and denoising.requires_grad):
        return torch.ones((), device=denoising.device)
    (trajectory_grad,) = torch.autograd.grad(trajectory, layer, retain_graph=True, allow_unused=True)
    (denoising_grad,) = torch.autograd.grad(denoising, layer, retain_graph=True, allow_unused=True)
    if trajectory_grad is None or denoising_grad is None:
        return torch.ones((), device=denoising.device)
    scale = trajectory_grad.norm() / (denoising_grad.norm() + ADAPTIVE_EPSILON)
    return scale.clamp(0.0, ADAPTIVE_MAX).detach()


def warm_start(student: ConditionalUNet1D, teacher: ConditionalUNet1D) -> None:
    """Copy the teacher's weights into the student, the target level's FiLM columns set to zero.

    Args:
        student: a U-Net with two noise-level inputs and the teacher's shape.
        teacher: a U-Net with one noise-level input.

    Raises:
        ValueError: the two U-Nets differ in shape beyond the second noise-level input.
    """
    step_dim = teacher.config.step_embedding_dim
    state = {}
    student_state = student.state_dict()
    for name, value in teacher.state_dict().items():
        target = student_state.get(name)
        if target is None:
            raise ValueError(f"the student's U-Net has no entry {name!r}; it must have the teacher's shape")
        if name.endswith("film.weight") and target.shape[1] == value.shape[1] + step_dim:
            zeros = value.new_zeros(value.shape[0], step_dim)
            value = torch.cat((value[:, :step_dim], zeros, value[:, step_dim:]), dim=1)
        if value.shape != target.shape:
            raise ValueError(
                f"U-Net entry {name!r} is {tuple(value.shape)} in the teacher and {tuple(target.shape)} in the "
                "student; they must have the same shape"
            )
        state[name] = value
    student.load_state_dict(state, strict=True)


class Distillation(nn.Module):
    """The frozen teacher U-Net, the target network and the two losses.

    Args:
        teacher: the teacher's U-Net (one noise-level input), frozen here.
        student: the student's U-Net; the target network starts as its copy.
        schedule: the teacher's noise levels and preconditioning.
        num_levels: N of the discretization.
        teacher_steps: most teacher Heun steps per sample.
        target_decay: EMA decay of the target network per optimizer step.
        log_sigma_mean: mean of ln(sigma) of the denoising loss's log-normal half.
        log_sigma_std: its standard deviation.
    """

    def __init__(
        self,
        teacher: ConditionalUNet1D,
        student: ConditionalUNet1D,
        schedule: KarrasSchedule,
        num_levels: int,
        teacher_steps: int,
        target_decay: float,
        log_sigma_mean: float,
        log_sigma_std: float,
    ) -> None:
        super().__init__()
        self.teacher = teacher.eval().requires_grad_(False)
        self.target = ConditionalUNet1D(
            student.config, student.action_dim, student.obs_dim, student.obs_steps, student.num_step_inputs
        )
        self.target.load_state_dict(student.state_dict())
        self.target.eval().requires_grad_(False)
        self.schedule = schedule
        self.num_levels = num_levels
        self.teacher_steps = teacher_steps
        self.target_decay = target_decay
        self.log_sigma_mean = log_sigma_mean
        self.log_sigma_std = log_sigma_std

    def train(self, mode: bool = True) -> "Distillation":
        """The teacher and the target network stay in eval mode."""
        return super().train(False)

    @torch.no_grad()
    def update_target(self, student: ConditionalUNet1D) -> None:
        """Move the target network towards the student's weights: target <- decay target + (1 - decay) student."""
        for target, current in zip(self.target.parameters(), student.parameters(), strict=True):
            target.lerp_(current, 1.0 - self.target_decay)

    def teacher_denoise(self, noisy: torch.Tensor, sigma: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """The teacher's D(x, sigma) (B, H, A)."""
        scalings = self.schedule.preconditioning(sigma)
        output = self.teacher(noisy * expand_like(scalings.c_in, noisy), scalings.c_noise, features)
        return expand_like(scalings.c_skip, noisy) * noisy + expand_like(scalings.c_out, noisy) * output

    def positions(self, count: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(start t, target s, middle u) positions (count,) long each: t <= u <= s, u <= t + teacher_steps."""
        levels = self.num_levels
        start = torch.randint(0, levels, (count,), device=device)
        target = start + (torch.rand(count, device=device) * (levels + 1 - start)).long()
        middle = start + (torch.rand(count, device=device) * (target - start + 1)).long()
        return start, target, torch.minimum(middle, start + self.teacher_steps)

    def denoising_levels(self, count: int, device: torch.device) -> torch.Tensor:
        """(count,) levels of the denoising loss: the first half from the upper 70%, the rest log-normal."""
        upper = (count + 1) // 2
        fraction = torch.rand(upper, device=device) * DENOISING_RHO_SPAN
        high = self.schedule.levels(fraction * (self.num_levels - 1), self.num_levels).to(device)
        low = self.schedule.log_normal_levels(count - upper, self.log_sigma_mean, self.log_sigma_std, None, device)
        return torch.cat((high, low))

    def forward(self, student, batch: dict[str, torch.Tensor]) -> DistillationLosses:
        """Both losses of one batch; first moves the target network (an update per optimizer step).

        Args:
            student: the `ConsistencyPolicy` being trained.
            batch: `obs` (b, To, Do) and `actions` (b, H, A) normalized; `images` for an image policy.
        """
        self.update_target(student.unet)
        actions = batch["actions"]
        features = student.batch_features(batch)  # (b, To, F)
        count, device = actions.shape[0], actions.device
        schedule, levels = self.schedule, self.num_levels
        floor = torch.full((count,), schedule.sigma_min, device=device)

        start, target, middle = self.positions(count, device)
        start_sigma, target_sigma = (
            schedule.levels(start, levels).to(device),
            schedule.levels(target, levels).to(device),
        )
        noisy = actions + expand_like(start_sigma, actions) * torch.randn_like(actions)
        with torch.no_grad():
            carried = noisy
            for offset in range(self.teacher_steps):
                current = torch.minimum(start + offset, middle)
                following = torch.minimum(start + offset + 1, middle)
                carried = heun_step(
                    lambda x, sigma: self.teacher_denoise(x, sigma, features),
                    carried,
                    schedule.levels(current, levels).to(device),
                    schedule.levels(following, levels).to(device),
                )
            middle_sigma = schedule.levels(middle, levels).to(device)
            reference = student.jump(carried, middle_sigma, target_sigma, features, self.target)
            reference = student.jump(reference, target_sigma, floor, features, self.target)
        jumped = student.jump(noisy, start_sigma, target_sigma, features)
        jumped = student.jump(jumped, target_sigma, floor, features, self.target)
        trajectory = pseudo_huber(jumped, reference)

        sigma = self.denoising_levels(count, device)
        noisy = actions + expand_like(sigma, actions) * torch.randn_like(actions)
        denoised = student.denoise(noisy, sigma, sigma, features)
        denoising = pseudo_huber(denoised, actions, schedule.loss_weight(sigma))
        output_layer = student.unet.final[-1].weight  # the U-Net's last 1x1 convolution, (A, C, 1)
        scale = adaptive_scale(trajectory, denoising, output_layer)
        return DistillationLosses(trajectory, denoising, scale)
