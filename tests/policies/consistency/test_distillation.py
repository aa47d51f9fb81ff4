"""The distilled student on a 1-D bimodal toy: one jump from sigma_max lands on both modes, not on their mean."""

import numpy as np
import pytest
import torch

from carp.data.normalizer import MinMaxNormalizer
from carp.policies.consistency.distillation import Distillation, adaptive_scale, warm_start
from carp.policies.consistency.family import build_student, build_teacher
from carp.policies.context import PolicyContext
from tests.policies.consistency.factories import tiny_student_config, tiny_teacher_config

MODE = 0.7
HORIZON = 4


class ExactTeacher(Distillation):
    """The distillation with the toy's exact denoiser in place of a trained teacher U-Net.

    Every chunk is all +MODE or all -MODE with equal odds, so E[x_0 | x] = MODE tanh(MODE sum(x) / sigma^2).
    """

    def teacher_denoise(self, noisy: torch.Tensor, sigma: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        total = noisy.sum(dim=(1, 2), keepdim=True)
        return (MODE * torch.tanh(MODE * total / sigma.reshape(-1, 1, 1) ** 2)).expand_as(noisy)


def toy_batch(count: int) -> dict[str, torch.Tensor]:
    signs = torch.where(torch.rand(count) < 0.5, -1.0, 1.0)
    return {"obs": torch.zeros(count, 1, 1), "actions": (MODE * signs).reshape(-1, 1, 1).expand(count, HORIZON, 1)}


def test_the_adaptive_scale_balances_the_two_gradients_at_the_layer():
    layer = torch.nn.Parameter(torch.tensor([1.0, 2.0]))
    trajectory = (layer**2).sum()  # gradient (2, 4)
    denoising = 10 * layer.sum()  # gradient (10, 10)
    scale = adaptive_scale(trajectory, denoising, layer)
    assert not scale.requires_grad
    torch.testing.assert_close(scale, torch.tensor(20**0.5 / (200**0.5 + 1e-4)))


@pytest.mark.slow
def test_the_one_step_student_reproduces_both_modes_of_a_bimodal_toy():
    torch.manual_seed(0)
    unit = MinMaxNormalizer(np.array([-1.0]), np.array([1.0]))
    context = PolicyContext(unit, unit, 1, HORIZON)
    shape = {"num_groups": 4}
    teacher = build_teacher(tiny_teacher_config(**shape), context)
    student = build_student(tiny_student_config(**shape, num_levels=8, teacher_steps=2, target_decay=0.9), context)
    warm_start(student.unet, teacher.unet)
    config = student.config
    distillation = ExactTeacher(
        teacher.unet, student.unet, student.schedule, config.num_levels, config.teacher_steps, config.target_decay,
        -1.2, 1.2,
    )  # fmt: skip
    optimizer = torch.optim.Adam(student.unet.parameters(), lr=1e-3)
    for _ in range(200):
        loss = distillation(student, toy_batch(64)).total(config.trajectory_weight, config.denoising_weight)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    student.train(False)
    obs = np.zeros((400, 1, 1), np.float32)
    chunks = student.predict_action(obs, generator=torch.Generator().manual_seed(1))[:, :, 0].mean(axis=1)
    near_plus, near_minus = np.mean(abs(chunks - MODE) < 0.15), np.mean(abs(chunks + MODE) < 0.15)
    assert student.model_calls_per_chunk == 1
    assert near_plus > 0.25 and near_minus > 0.25, (near_plus, near_minus, np.histogram(chunks, 8, (-1, 1))[0])
