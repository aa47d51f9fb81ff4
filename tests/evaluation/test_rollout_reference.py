"""What evaluation executes for given CARP weights, pinned by a stored Can rollout.

A small policy whose weights come from a fixed seed is rolled out for a few chunks on one Can seed through the path an
evaluation takes (`Policy.deployment`, `PolicySource`, `run_episode`), once per backend. The observations each
decision sees and the actions it executes must match `REFERENCE_FILE`. A change to the episode reset, the observation
history and its padding after a reset, the order of the observation keys, normalization, token choice, decoding, the
executed part of the chunk, the rotation conversion or the controller shows up here as a mismatch, while a change
that leaves every rollout as it was does not. After a deliberate change of behaviour, or an upgrade of robosuite,
MuJoCo or PyTorch that moves the numbers, regenerate the file with :func:`write_reference` and say why in the commit.
"""

import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

from carp.data.normalizer import MinMaxNormalizer
from carp.data.rotation import ROT6D_ACTION_DIM
from carp.evaluation.rollout import run_episode
from carp.evaluation.runner import deploy
from carp.evaluation.sources import PolicySource
from carp.policies.carp.config import CarpConfig
from carp.policies.carp.policy import CarpPolicy
from carp.policies.carp.spec import PolicySpec
from carp.tasks import get_task
from carp.tasks.arms import simulation
from carp.tasks.arms.task import ABSOLUTE_ACTIONS
from carp.tokenizer.artifact import TokenizerArtifact
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer
from tests.policies.carp.factories import scrambled_transformer

REFERENCE_FILE = Path(__file__).parent / "data" / "can_rollout_reference.npz"
TASK = "can"
EPISODE_SEED = 100000  # the first evaluation seed of the default params
OBS_KEYS = ("object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
OBS_STEPS = 2
ACTION_STEPS = 8
CHUNKS = 4
# ONNX Runtime and PyTorch evaluate the same float32 computation in another order, and other CPUs round PyTorch's
# kernels differently: the executed actions then differ by float32 rounding carried through a few chunks of closed
# loop, a few 1e-6 in the actions' units (metres, radians, gripper command). A changed decision (another executed
# slice, key order, rotation convention or episode seed) moves them by more than 1. Rounding cannot change a token:
# the closest greedy choice of this rollout is won by a logit margin of 2.5e-4, far above float32 rounding.
TOLERANCE = 1e-4


def reference_policy() -> CarpPolicy:
    """CARP at the default shapes (To = 2, H = 16, scales 1-4, 10-D absolute actions, Can's Do) with a small network.

    Weights from seed 0, spread out (`scrambled_transformer`, a codebook of unit normals) so that the chosen tokens,
    hence the actions, depend on the observations. Fixed normalizer statistics: observations within +-1.5, actions in
    the Panda's workspace above the table, any 6-D rotation and gripper command.
    """
    torch.manual_seed(0)
    tokenizer = MultiScaleActionTokenizer(
        TokenizerSpec(action_dim=ROT6D_ACTION_DIM, codebook_size=64, latent_channels=4)
    )
    with torch.no_grad():
        tokenizer.quantizer.codebook.normal_()
    spec = PolicySpec(
        obs_dim=get_task(TASK).low_dim_obs_dim,
        obs_steps=OBS_STEPS,
        action_dim=ROT6D_ACTION_DIM,
        scales=tokenizer.spec.scales,
        latent_channels=tokenizer.spec.latent_channels,
        codebook_size=tokenizer.spec.codebook_size,
        config=CarpConfig(depth=2, width=32, num_heads=4),
    )
    obs_dim = spec.obs_dim
    action_normalizer = MinMaxNormalizer(
        np.array([-0.25, -0.35, 0.82] + [-1.0] * 7), np.array([0.25, 0.35, 1.15] + [1.0] * 7)
    )
    return CarpPolicy(
        TokenizerArtifact.build(tokenizer.eval(), {TASK: action_normalizer}, "test-abs10"),
        scrambled_transformer(spec, seed=0),
        MinMaxNormalizer(np.full(obs_dim, -1.5), np.full(obs_dim, 1.5)),
        action_normalizer,
    )


class RecordingSource:
    """Passes a source's decisions through and keeps what each one saw and executed."""

    def __init__(self, source: PolicySource) -> None:
        self.source = source
        self.observations: list[np.ndarray] = []
        self.actions: list[np.ndarray] = []

    def reset(self, env, seed: int) -> None:
        self.source.reset(env, seed)

    def act(self, observation_history: np.ndarray, env) -> tuple[np.ndarray, None]:
        actions, _ = self.source.act(observation_history, env)
        self.observations.append(observation_history.copy())
        self.actions.append(actions.copy())
        return actions, None


def record_rollout(env, backend: str, directory: Path) -> dict[str, np.ndarray]:
    """Roll `reference_policy` out for `CHUNKS` chunks on `EPISODE_SEED` with `backend`, as an evaluation does.

    Returns:
        ``observations`` (CHUNKS, To, Do) float64, the history each decision saw; ``actions`` (CHUNKS, Ta, 7)
        float64, what the env executed; ``backend``, the backend that ran.
    """
    policy = reference_policy()
    checkpoint = directory / "policy.pt"
    policy.save(checkpoint)
    deployment = deploy(policy, checkpoint, backend, directory)
    source = PolicySource(deployment.load, ABSOLUTE_ACTIONS, OBS_STEPS, ACTION_STEPS, inference={"top_k": 1})
    recorder = RecordingSource(source)
    result = run_episode(get_task(TASK), env, recorder, EPISODE_SEED, OBS_KEYS, OBS_STEPS, CHUNKS * ACTION_STEPS)
    assert result.error == "" and result.steps == CHUNKS * ACTION_STEPS
    return {
        "observations": np.stack(recorder.observations),
        "actions": np.stack(recorder.actions),
        "backend": np.array(deployment.backend),
    }


def write_reference(path: Path = REFERENCE_FILE) -> Path:
    """Record the reference rollout with the PyTorch policy into `path` (the test's stored file by default).

    Run it from the repository root only after a deliberate change of what a rollout executes:
    ``python -c "from tests.evaluation.test_rollout_reference import write_reference; write_reference()"``.
    """
    env = simulation.make_env(get_task(TASK).make_env_args("absolute"))
    try:
        with tempfile.TemporaryDirectory() as directory:
            recorded = record_rollout(env, "torch", Path(directory))
    finally:
        env.close()
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, observations=recorded["observations"], actions=recorded["actions"])
    return path


@pytest.fixture(scope="module")
def can_env():
    env = simulation.make_env(get_task(TASK).make_env_args("absolute"))
    yield env
    env.close()


@pytest.fixture(scope="module")
def reference() -> dict[str, np.ndarray]:
    with np.load(REFERENCE_FILE) as stored:
        return {key: stored[key] for key in stored.files}


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["torch", "onnxruntime"])
def test_rollout_sees_and_executes_the_reference(can_env, reference, backend, tmp_path):
    recorded = record_rollout(can_env, backend, tmp_path)
    assert str(recorded["backend"]) == backend
    observations, actions = recorded["observations"], recorded["actions"]
    assert observations.shape == reference["observations"].shape == (CHUNKS, OBS_STEPS, get_task(TASK).low_dim_obs_dim)
    assert actions.shape == reference["actions"].shape == (CHUNKS, ACTION_STEPS, 7)
    # After the reset the history repeats the first observation, which depends on the episode seed only: no policy
    # rounding reaches it, so it is compared at float64 precision.
    np.testing.assert_array_equal(observations[0, 0], observations[0, 1])
    np.testing.assert_allclose(observations[0], reference["observations"][0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(actions, reference["actions"], rtol=0, atol=TOLERANCE)
    np.testing.assert_allclose(observations, reference["observations"], rtol=0, atol=TOLERANCE)


def test_reference_actions_vary_between_chunks(reference):
    """A policy that repeated one chunk whatever it saw would pin nothing about observations reaching it."""
    actions = reference["actions"]
    assert np.ptp(actions[:, :, :3], axis=(0, 1)).min() > 1e-2  # positions spread over centimetres
    assert len({chunk.round(3).tobytes() for chunk in actions}) == CHUNKS
