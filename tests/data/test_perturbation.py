import numpy as np
import pytest

from carp import simulation
from carp.data.collect import run_expert_episode
from carp.data.experts import GRIPPER_CLOSED, make_expert
from carp.data.perturbation import CorrelatedOffset, ExpertNoise

NOISE = ExpertNoise(position_m=0.01, rotation_rad=0.05)


def test_offset_has_the_requested_spread_and_correlation():
    offsets = CorrelatedOffset(NOISE, np.random.default_rng(0))
    samples = np.array([np.concatenate(offsets.step(driven=True)) for _ in range(60_000)])[1_000:]
    np.testing.assert_allclose(samples[:, :3].std(axis=0), 0.01, rtol=0.1)
    np.testing.assert_allclose(samples[:, 3:].std(axis=0), 0.05, rtol=0.1)
    lag_one = [np.corrcoef(samples[:-1, axis], samples[1:, axis])[0, 1] for axis in range(6)]
    np.testing.assert_allclose(lag_one, NOISE.correlation, atol=0.02)


def test_offset_decays_geometrically_outside_free_space():
    offsets = CorrelatedOffset(NOISE, np.random.default_rng(1))
    for _ in range(20):
        offsets.step(driven=True)
    before = offsets.offset.copy()
    position, rotation = offsets.step(driven=False)
    np.testing.assert_allclose(np.concatenate([position, rotation]), NOISE.contact_decay * before, rtol=1e-12)
    for _ in range(60):
        offsets.step(driven=False)
    assert np.abs(offsets.offset).max() < 1e-9


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [({"position_m": -1.0}, "must be >= 0"), ({"correlation": 1.0}, r"must be in \[0, 1\)")],
)
def test_bad_noise_settings_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ExpertNoise(**kwargs)


def run_recording_executed(noise: ExpertNoise | None, seed: int):
    """One Lift expert episode; returns the episode, success and the actions the env actually executed."""
    env = simulation.make_env(simulation.make_env_args("lift"))
    executed = []
    step = env.step

    def recording_step(action):
        executed.append(np.array(action))
        return step(action)

    env.step = recording_step
    try:
        episode, success = run_expert_episode(env, make_expert("lift", env), seed, max_steps=200, noise=noise)
    finally:
        env.close()
    return episode, success, np.stack(executed)


def test_noisy_demo_records_the_clean_command_and_executes_the_perturbed_one():
    episode, success, executed = run_recording_executed(NOISE, seed=31)
    assert success
    recorded = episode.actions
    assert executed.shape == recorded.shape
    # The gripper is never perturbed; the pose is, by about the requested size, mostly while moving freely.
    np.testing.assert_array_equal(executed[:, 6], recorded[:, 6])
    position_offsets = np.linalg.norm(executed[:, :3] - recorded[:, :3], axis=1)
    assert 0.004 < position_offsets.max() < 0.06
    # The clean command keeps the expert's bounded step per control step, which a recorded perturbed pose would break.
    assert np.linalg.norm(np.diff(recorded[:, :3], axis=0), axis=1).max() <= 0.0161
    # While the gripper closes the offset has decayed to a fraction of its free-space size.
    closing = np.flatnonzero(recorded[:, 6] == GRIPPER_CLOSED)[:10]
    assert position_offsets[closing[-1]] < 0.5 * position_offsets.max()
    again, _, executed_again = run_recording_executed(NOISE, seed=31)
    np.testing.assert_array_equal(again.actions, recorded)
    np.testing.assert_array_equal(executed_again, executed)


def test_without_noise_the_executed_actions_are_the_recorded_ones():
    for noise in (None, ExpertNoise()):
        episode, success, executed = run_recording_executed(noise, seed=31)
        assert success
        np.testing.assert_array_equal(executed, episode.actions)
