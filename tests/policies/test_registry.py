"""The policy seam: every family builds from tiny params, trains, saves and loads through `load_policy` unchanged."""

import dataclasses
import functools
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from carp.config import TrainingConfig
from carp.data.normalizer import MinMaxNormalizer
from carp.evaluation.sources import PolicySource
from carp.policies.carp.config import CarpConfig
from carp.policies.context import PolicyContext
from carp.policies.diffusion.config import DiffusionTransformerConfig, DiffusionUNetConfig
from carp.policies.next_token.config import NextTokenConfig
from carp.policies.registry import (
    FAMILY_MODULES,
    average_policies,
    build_policy,
    family_names,
    get_family,
    load_policy,
    register_family,
    train_policy,
    unregister_family,
)
from carp.policies.sections import SECTION_MODULES, get_sections, teacher_of
from carp.tasks.arms.task import DELTA_ACTIONS
from carp.training.checkpoint import CheckpointError
from carp.training.loop import PolicyTrainingData
from tests.policies.carp.factories import OBS_DIM, OBS_STEPS, tiny_artifact, tiny_policy, tiny_tokenizer
from tests.policies.consistency.factories import tiny_student_config, tiny_teacher_config
from tests.policies.stub_family import STUB_FAMILY, StubConfig
from tests.policies.vq_bet.factories import tiny_config as vq_bet_config

REPO = Path(__file__).resolve().parents[2]

TINY_CONFIGS = {
    "carp": CarpConfig(depth=1, width=16, num_heads=2),
    "diffusion_unet": DiffusionUNetConfig(
        down_dims=(16, 32), kernel_size=3, num_groups=8, step_embedding_dim=16, num_train_steps=10, warmup_steps=0
    ),
    "diffusion_transformer": DiffusionTransformerConfig(
        num_layers=1, num_heads=2, width=16, num_train_steps=10, warmup_steps=0, attention_dropout=0.0
    ),
    "next_token": NextTokenConfig(depth=1, width=16, num_heads=2, warmup_steps=0),
    "vq_bet": vq_bet_config(),
    "edm_unet": tiny_teacher_config(),
    "consistency_policy": tiny_student_config(),
}
TINY_INFERENCE = {
    "diffusion_unet": {"sampler": "ddim", "num_inference_steps": 4},
    "diffusion_transformer": {"sampler": "ddpm", "num_inference_steps": 10},
    "next_token": {"top_k": 3},
    "vq_bet": {"code_choice": "sample"},
    "edm_unet": {"num_levels": 4},
    "consistency_policy": {"chain_levels": (3, 6)},
}


def tiny_context() -> PolicyContext:
    """Do = 3, To = 2, A = 2, H = 8, with the tiny tokenizer of `tests.policies.carp.factories`."""
    policy = tiny_policy()
    return PolicyContext(
        obs_normalizer=policy.obs_normalizer,
        action_normalizer=policy.action_normalizer,
        obs_steps=OBS_STEPS,
        action_horizon=8,
        tokenizer_artifact=tiny_artifact(tiny_tokenizer()),
        metadata={"task": "lift"},
    )


def tiny_data(count: int = 16) -> PolicyTrainingData:
    """Normalized random windows of the tiny shapes: obs (N, 2, 3), actions (N, 8, 2) in [-1, 1]."""
    generator = torch.Generator().manual_seed(0)
    return PolicyTrainingData(
        torch.rand(count, OBS_STEPS, OBS_DIM, generator=generator) * 2 - 1,
        torch.rand(count, 8, 2, generator=generator) * 2 - 1,
    )


@pytest.fixture(autouse=True)
def stub_registered():
    register_family(STUB_FAMILY)
    yield
    unregister_family(STUB_FAMILY.name)


@pytest.mark.parametrize("name", [*TINY_CONFIGS, STUB_FAMILY.name])
def test_every_family_trains_saves_and_round_trips_through_load_policy(name, tmp_path):
    config = TINY_CONFIGS.get(name) or get_family(name).config_class()
    training = TrainingConfig(epochs=2, batch_size=8, checkpoint_every=1)
    teacher = None
    teacher_family = get_family(name).teacher
    if teacher_family is not None:
        # A distilled family is given its teacher family's trained policy.
        teacher = train_policy(
            teacher_family, TINY_CONFIGS[teacher_family], training, tiny_context(), tiny_data(), tmp_path / "teacher"
        )
    history = []
    policy = train_policy(
        name,
        config,
        training,
        tiny_context(),
        tiny_data(),
        tmp_path / "state",
        on_epoch_end=lambda e, m: history.append(m),
        teacher=teacher,
    )
    assert len(history) == 2 and all(np.isfinite(epoch["loss"]) and epoch["epoch_seconds"] > 0 for epoch in history)
    untrained = build_policy(name, config, tiny_context())
    changed = [
        not torch.equal(trained, fresh)
        for trained, fresh in zip(policy.state_dict().values(), untrained.state_dict().values(), strict=True)
    ]
    assert any(changed), "training left every weight at its initial value"
    policy.configure_inference(**TINY_INFERENCE.get(name, {}))
    path = tmp_path / "policy.pt"
    policy.save(path)
    loaded = load_policy(path)
    loaded.configure_inference(**TINY_INFERENCE.get(name, {}))
    assert type(loaded) is type(policy) and loaded.policy_type == name
    # The context's metadata, plus what a family records of its training (CARP: its attention kernel).
    assert loaded.metadata == policy.metadata and loaded.metadata["task"] == "lift"
    assert loaded.num_parameters == policy.num_parameters > 0
    assert loaded.description == policy.description
    obs = np.random.default_rng(1).normal(size=(4, OBS_STEPS, OBS_DIM)).astype(np.float32)
    before = policy.predict_action_timed(obs, generator=torch.Generator().manual_seed(3))
    after = loaded.predict_action_timed(obs, generator=torch.Generator().manual_seed(3))
    np.testing.assert_array_equal(after.actions, before.actions)
    assert before.actions.shape == (4, 8, 2) and before.actions.dtype == np.float32
    assert after.model_calls == loaded.model_calls_per_chunk >= 1
    # An interrupted run of the same setup resumes from its state: a second call trains no further epochs.
    replayed = []
    train_policy(
        name,
        config,
        training,
        tiny_context(),
        tiny_data(),
        tmp_path / "state",
        on_epoch_end=lambda e, m: replayed.append(m),
        teacher=teacher,
    )
    assert replayed == history


def test_model_calls_per_chunk_are_the_familys_sequential_steps():
    context = tiny_context()
    expected = {
        "carp": 2,
        "diffusion_unet": 4,
        "diffusion_transformer": 10,
        "next_token": 2 * (1 + 2),
        "vq_bet": 1,
        "edm_unet": 2 * (4 - 1),
        "consistency_policy": 3,
    }
    for name, calls in expected.items():
        policy = build_policy(name, TINY_CONFIGS[name], context)
        policy.configure_inference(**TINY_INFERENCE.get(name, {}))
        assert policy.model_calls_per_chunk == calls, name
    assert build_policy("diffusion_unet", TINY_CONFIGS["diffusion_unet"], context).description == "DDPM-10"


def test_the_stub_family_acts_through_the_evaluation_source(tmp_path):
    policy = build_policy(STUB_FAMILY.name, STUB_FAMILY.config_class(), tiny_context())
    path = tmp_path / "policy.pt"
    policy.save(path)
    deployment = policy.deployment(path, "onnxruntime", tmp_path / "graphs")
    assert deployment.backend == "torch"
    source = PolicySource(deployment.load, action_format=DELTA_ACTIONS, obs_steps=OBS_STEPS, action_steps=4)
    source.reset(env=None, seed=0)
    actions, timing = source.act(np.zeros((OBS_STEPS, OBS_DIM)), env=None)
    assert actions.shape == (4, 2) and timing.prediction >= 0


def test_carp_checkpoints_name_their_family(tmp_path):
    path = tmp_path / "policy.pt"
    tiny_policy().save(path)
    checkpoint = torch.load(path, weights_only=True)
    assert checkpoint["policy_type"] == "carp" and checkpoint["format_version"] == 3


def test_the_two_halves_of_the_family_table_agree_and_sections_load_without_the_models():
    assert list(SECTION_MODULES) == list(FAMILY_MODULES)
    for name in FAMILY_MODULES:
        family = get_family(name)
        assert (family.config_class, family.inference_class) == get_sections(name), name
        assert family.teacher == teacher_of(name)
    assert teacher_of("consistency_policy") == "edm_unet" and teacher_of("carp") is None
    # Validating params never imports a family's model code or torch.
    script = (
        "import sys; import carp.config as c; c.load_params('params.yaml'); "
        "print(sorted(m for m in sys.modules if m == 'torch' or m.endswith('.family')))"
    )
    loaded = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True, cwd=REPO)
    assert loaded.stdout.strip() == "[]"


def test_an_unknown_family_is_refused_with_the_known_ones_named():
    with pytest.raises(KeyError, match=r"unknown policy family 'lstm' \(known: carp"):
        get_family("lstm")
    assert family_names()[0] == "carp"


def test_a_checkpoint_of_an_unknown_family_is_one_line_naming_the_file(tmp_path):
    path = tmp_path / "policy.pt"
    checkpoint = tiny_policy().to_checkpoint() | {"policy_type": "lstm"}
    torch.save(checkpoint, path)
    with pytest.raises(CheckpointError, match=r"policy_type='lstm': unknown policy family 'lstm'") as raised:
        load_policy(path)
    assert str(raised.value).startswith(f"{path}: ")


def test_inference_settings_are_the_familys_own(tmp_path):
    policy = tiny_policy()
    policy.configure_inference(top_k=3)
    assert policy.description == "top-3"
    with pytest.raises(TypeError, match="num_inference_steps"):
        policy.configure_inference(num_inference_steps=10)
    path = tmp_path / "policy.pt"
    policy.save(path)
    source = functools.partial(PolicySource, functools.partial(load_policy, path), "delta", OBS_STEPS, 4)
    with pytest.raises(ValueError, match="top_k"):
        source(inference={"top_k": 99})


@pytest.mark.slow
def test_the_stub_family_runs_through_the_library_evaluation(tmp_path):
    """Train, save and evaluate a family defined in a test file, in simulation, with no change outside that file."""
    from carp.evaluation.runner import EvaluationSetup, evaluate_policy
    from carp.tasks import get_task

    obs_keys = ["object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos"]  # Do = 19 on Lift
    shapes = PolicyContext(
        obs_normalizer=MinMaxNormalizer(np.full(19, -1.0), np.full(19, 1.0)),
        action_normalizer=MinMaxNormalizer(np.full(7, -0.05), np.full(7, 0.05)),  # small delta actions
        obs_steps=2,
        action_horizon=8,
    )
    data = PolicyTrainingData(torch.zeros(8, 2, 19), torch.zeros(8, 8, 7))
    training = TrainingConfig(epochs=1, batch_size=8)
    policy = train_policy(STUB_FAMILY.name, StubConfig(), training, shapes, data, tmp_path / "state")
    path = tmp_path / "policy.pt"
    policy.save(path)
    setup = EvaluationSetup(
        env_args=get_task("lift").make_env_args("delta"),
        action_format=DELTA_ACTIONS,
        obs_keys=obs_keys,
        obs_steps=2,
        action_steps=4,
        max_steps=12,
    )

    def evaluate(**changes):
        return evaluate_policy(path, [100_000], dataclasses.replace(setup, **changes))

    summary, results = evaluate()
    assert summary["episodes"] == 1 and summary["policy_type"] == "stub" and summary["backend"] == "torch"
    assert summary["inference"] == "linear" and summary["model_calls_per_chunk"] == 1
    assert results[0].steps == 12 and not results[0].error and len(results[0].prediction_seconds) == 3
    # With temporal ensembling every control step predicts a chunk, and the summary says so.
    summary, results = evaluate(ensemble_m=0.0)
    assert (summary["ensemble_m"], summary["action_steps"]) == (0.0, 1)
    assert results[0].steps == 12 and not results[0].error and len(results[0].prediction_seconds) == 12


def test_averaging_snapshots_gives_the_mean_weights_and_refuses_other_runs(tmp_path):
    paths = [tmp_path / f"epoch{index}.pt" for index in range(3)]
    for offset, path in enumerate(paths):
        policy = tiny_policy()
        with torch.no_grad():
            for parameter in policy.transformer.parameters():
                parameter.add_(float(offset))
        policy.save(path)
    reference = tiny_policy()
    averaged = average_policies(paths)
    for name, value in reference.transformer.state_dict().items():
        expected = (
            value + 1.0
            if value.is_floating_point() and name in dict(reference.transformer.named_parameters())
            else value
        )
        torch.testing.assert_close(averaged.transformer.state_dict()[name], expected, rtol=0, atol=1e-6, msg=name)
    assert averaged.metadata == reference.metadata
    # Snapshots of another architecture do not average.
    tiny_policy(width=32).save(tmp_path / "other.pt")
    with pytest.raises(ValueError, match="does not match"):
        average_policies([paths[0], tmp_path / "other.pt"])
    with pytest.raises(ValueError, match="no checkpoint to average"):
        average_policies([])


@pytest.mark.parametrize(
    "name, draws, greedy",
    [
        ("carp", {"top_k": 2}, {"top_k": 1}),
        ("next_token", {"top_k": 3}, {"top_k": 1}),
        ("vq_bet", {"code_choice": "sample"}, {"code_choice": "greedy"}),
        ("diffusion_unet", {"sampler": "ddim", "num_inference_steps": 4}, None),
        ("diffusion_transformer", {"sampler": "ddpm", "num_inference_steps": 10}, None),
    ],
)
def test_draws_random_says_whether_the_generator_changes_the_chunk(name, draws, greedy):
    policy = build_policy(name, TINY_CONFIGS[name], tiny_context())
    obs = np.random.default_rng(2).normal(size=(3, OBS_STEPS, OBS_DIM)).astype(np.float32)

    def two_seeds_differ() -> bool:
        chunks = [policy.predict_action(obs, generator=torch.Generator().manual_seed(seed)) for seed in (0, 1)]
        return not np.array_equal(*chunks)

    policy.configure_inference(**draws)
    assert policy.draws_random and two_seeds_differ()
    if greedy is not None:  # diffusion always starts from drawn noise
        policy.configure_inference(**greedy)
        assert not policy.draws_random and not two_seeds_differ()
