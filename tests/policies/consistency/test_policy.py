"""The teacher and student policies: warm start, seeded sampling, model calls, config checks, distillation errors."""

import numpy as np
import pytest
import torch

from carp.config import ConfigError, TrainingConfig
from carp.policies.consistency.distillation import Distillation, warm_start
from carp.policies.consistency.family import build_student, build_teacher
from carp.policies.consistency.policy import schedule_of
from carp.policies.diffusion.unet import ConditionalUNet1D
from carp.policies.registry import train_policy
from tests.policies.consistency.factories import tiny_student_config, tiny_teacher_config
from tests.policies.test_registry import tiny_context, tiny_data

OBS = np.random.default_rng(0).normal(size=(5, 2, 3)).astype(np.float32)


def randomized(module: torch.nn.Module, seed: int) -> torch.nn.Module:
    """`module` with every weight redrawn, so that no zero-initialized part hides a wrong wiring."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for parameter in module.parameters():
            parameter.copy_(torch.randn(parameter.shape, generator=generator) * 0.3)
    return module


def test_the_warm_started_student_jumps_along_the_teachers_denoiser():
    """With the target level's FiLM columns at zero, G(x, t, s) = (s/t) x + (1 - s/t) D_teacher(x, t) for every s."""
    context = tiny_context()
    teacher = build_teacher(tiny_teacher_config(), context)
    randomized(teacher.unet, 0)
    student = build_student(tiny_student_config(), context)
    warm_start(student.unet, teacher.unet)
    generator = torch.Generator().manual_seed(1)
    noisy = torch.randn(4, 8, 2, generator=generator)
    features = torch.randn(4, 2, 3, generator=generator)
    sigma = torch.tensor([80.0, 5.0, 1.0, 0.3])
    denoised = teacher.denoise(noisy, sigma, features)
    for target in (torch.full((4,), 0.02), torch.tensor([10.0, 2.0, 0.5, 0.1])):
        expected = (target / sigma).reshape(-1, 1, 1) * noisy + (1 - target / sigma).reshape(-1, 1, 1) * denoised
        torch.testing.assert_close(student.jump(noisy, sigma, target, features), expected, rtol=1e-5, atol=1e-5)
    # A jump to the current level stays put.
    torch.testing.assert_close(student.jump(noisy, sigma, sigma, features), noisy)


def test_warm_start_refuses_a_teacher_of_another_shape():
    context = tiny_context()
    teacher = build_teacher(tiny_teacher_config(down_dims=(16, 32, 64)), context)
    student = build_student(tiny_student_config(), context)
    with pytest.raises(ValueError, match="same shape|no entry"):
        warm_start(student.unet, teacher.unet)


@pytest.mark.parametrize("build, config, settings", [
    (build_teacher, tiny_teacher_config(), {"num_levels": 4}),
    (build_student, tiny_student_config(), {"chain_levels": (3, 6)}),
])  # fmt: skip
def test_seeded_sampling_is_deterministic_and_clamped(build, config, settings):
    policy = randomized(build(config, tiny_context()), 2).train(False)
    policy.configure_inference(**settings)
    first = policy.predict_action_timed(OBS, generator=torch.Generator().manual_seed(5))
    second = policy.predict_action(OBS, generator=torch.Generator().manual_seed(5))
    other = policy.predict_action(OBS, generator=torch.Generator().manual_seed(6))
    np.testing.assert_array_equal(first.actions, second)
    assert not np.array_equal(first.actions, other)
    low, high = policy.action_normalizer.unnormalize(torch.tensor([-1.0, 1.0]).reshape(2, 1).expand(2, 2)).numpy()
    assert (first.actions >= low - 1e-6).all() and (first.actions <= high + 1e-6).all()
    assert first.model_calls == policy.model_calls_per_chunk


def test_model_calls_and_descriptions():
    context = tiny_context()
    teacher = build_teacher(tiny_teacher_config(), context)
    assert (teacher.model_calls_per_chunk, teacher.description) == (158, "Heun-80")
    teacher.configure_inference(num_levels=10)
    assert teacher.model_calls_per_chunk == 18
    student = build_student(tiny_student_config(), context)
    assert (student.model_calls_per_chunk, student.description) == (1, "1-step")
    student.configure_inference(chain_levels=[3, 6])
    assert (student.model_calls_per_chunk, student.description) == (3, "3-step")
    with pytest.raises(ValueError, match=r"chain_levels must be strictly increasing positions in \[1, 10\)"):
        student.configure_inference(chain_levels=[6, 3])
    with pytest.raises(ValueError, match="chain_levels"):
        student.configure_inference(chain_levels=[10])


def test_the_student_has_the_teachers_parameters_plus_one_step_embedding_per_film_projection():
    context = tiny_context()
    teacher = build_teacher(tiny_teacher_config(), context)
    student = build_student(tiny_student_config(), context)
    films = [module for name, module in student.unet.named_modules() if name.endswith("film")]
    assert student.num_parameters == teacher.num_parameters + sum(film.out_features * 16 for film in films)


def test_the_unet_refuses_the_wrong_number_of_noise_levels():
    unet = ConditionalUNet1D(tiny_student_config(), action_dim=2, obs_dim=3, obs_steps=2, num_step_inputs=2)
    with pytest.raises(ValueError, match=r"steps must have shape \(N,\) or \(N, 2\)"):
        unet(torch.zeros(4, 8, 2), torch.zeros(4), torch.zeros(4, 2, 3))
    assert unet(torch.zeros(4, 8, 2), torch.zeros(4, 2), torch.zeros(4, 2, 3)).shape == (4, 8, 2)


def test_distillation_positions_keep_their_order():
    context = tiny_context()
    teacher = build_teacher(tiny_teacher_config(), context)
    student = build_student(tiny_student_config(), context)
    distillation = Distillation(teacher.unet, student.unet, schedule_of(teacher.config), 10, 2, 0.0, -1.2, 1.2)
    torch.manual_seed(0)
    start, target, middle = distillation.positions(4096, torch.device("cpu"))
    assert bool(((start <= middle) & (middle <= target) & (target <= 10) & (middle <= start + 2)).all())
    assert start.min() == 0 and start.max() == 9 and target.max() == 10
    assert not any(p.requires_grad for p in distillation.parameters())


def test_the_student_needs_a_fitting_teacher(tmp_path):
    training = TrainingConfig(epochs=1, batch_size=8)
    with pytest.raises(ValueError, match="the run has no teacher"):
        train_policy("consistency_policy", tiny_student_config(), training, tiny_context(), tiny_data(), tmp_path)
    teacher = build_teacher(tiny_teacher_config(down_dims=(16, 32, 64)), tiny_context())
    with pytest.raises(ValueError, match=r"teacher's edm_unet.down_dims=\(16, 32, 64\) differs"):
        train_policy(
            "consistency_policy", tiny_student_config(), training, tiny_context(), tiny_data(), tmp_path / "s",
            teacher=teacher,
        )  # fmt: skip


def test_config_errors_name_the_key():
    with pytest.raises(ConfigError, match=r"edm_unet.sigma_max=0.01: must be > sigma_min=0.02"):
        tiny_teacher_config(sigma_max=0.01)
    with pytest.raises(ConfigError, match=r"consistency_policy.target_decay=1.0: must be in \[0, 1\)"):
        tiny_student_config(target_decay=1.0)
    with pytest.raises(ConfigError, match="edm_unet.kernel_size=4: must be odd"):
        tiny_teacher_config(kernel_size=4)


def test_params_refuse_a_student_whose_teacher_differs():
    from carp.config import Params

    with pytest.raises(ConfigError, match=r"consistency_policy.down_dims=\[64, 128, 256\]: must equal the teacher's"):
        Params(families={"consistency_policy": tiny_student_config(down_dims=(64, 128, 256))})
    # The student's stage trains its own teacher: edm_unet need not be listed, nor come first when it is.
    Params(policies=("consistency_policy",))
    Params(policies=("consistency_policy", "edm_unet"))
