"""Push-T through the library's pipeline steps: scripted collection into the robomimic schema, ingestion into the
replay buffer, evaluation of the expert in worker processes with DP's score and a video, and the refusal of files that
are not Push-T's."""

import functools
import json

import h5py
import numpy as np
import pytest

from carp.data.collect import collect_demonstrations
from carp.data.ingest import ingest_demonstrations
from carp.data.replay_buffer import ReplayBuffer
from carp.data.robomimic_io import DatasetError, read_demonstrations, write_demonstrations
from carp.evaluation.rollout import evaluate_episodes, run_episode
from carp.evaluation.sources import ExpertSource
from carp.tasks import get_task
from carp.tasks.pusht.env import ENV_NAME
from tests.conftest import make_episode

PUSHT = get_task("pusht")
OBS_KEYS = ("block_keypoints", "agent_pos")


@pytest.fixture(scope="module")
def pusht_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("pusht") / "pusht.hdf5"
    summary = collect_demonstrations("pusht", num_demos=2, output_path=path, seed=0, max_steps=500)
    return path, summary


@pytest.mark.slow
def test_collected_push_t_demos_are_successful_seeded_2_d_episodes_in_the_robomimic_schema(pusht_file, tmp_path):
    path, summary = pusht_file
    assert summary.kept == 2 and summary.attempted >= 2 and summary.seeds[0] >= 0
    demos = read_demonstrations(path, OBS_KEYS, action_dim=2, env_name=ENV_NAME)
    with h5py.File(path) as handle:
        attrs = dict(handle["data"].attrs)
    assert attrs["expert"] == "pusht_planner" and "gym_pusht_version" in attrs and "pymunk_version" in attrs
    assert attrs["max_steps"] == 300  # collection_max_steps above Push-T's limit is capped to it
    for episode in demos.episodes:
        assert episode.obs["block_keypoints"].shape == (episode.length, 18)
        assert episode.obs["agent_pos"].shape == (episode.length, 2)
        assert episode.states.shape == (episode.length, 5)
        assert episode.length <= 300 and episode.dones[-1] == 1
        # The stored reward is DP's: the last step reaches the full reward, earlier ones the coverage fraction.
        assert episode.rewards[-1] == 1.0 and np.all((episode.rewards >= 0) & (episode.rewards <= 1))
        assert np.all((episode.actions >= 0) & (episode.actions <= 512))
    # The first observation is DP's reset for the demo's seed.
    env = PUSHT.make_env(demos.env_args)
    first = PUSHT.reset(env, int(demos.episodes[0].attrs["seed"]))
    np.testing.assert_allclose(demos.episodes[0].obs["agent_pos"][0], first["agent_pos"])

    summary = ingest_demonstrations(path, tmp_path / "processed", OBS_KEYS, env_name=ENV_NAME)
    assert (summary.obs_dim, summary.action_dim) == (20, 2)
    buffer = ReplayBuffer.load(tmp_path / "processed" / "replay.zarr")
    np.testing.assert_allclose(buffer.action[: demos.episodes[0].length], demos.episodes[0].actions, rtol=1e-6)
    assert json.loads(json.dumps(buffer.attrs["env_args"]))["env_name"] == ENV_NAME


@pytest.mark.slow
def test_the_expert_evaluated_in_workers_succeeds_with_a_full_score_and_records_a_video():
    env_args = PUSHT.make_env_args("absolute")
    results = evaluate_episodes(
        env_args, functools.partial(ExpertSource, "pusht"), [100000, 100001], OBS_KEYS, 2, 300, workers=2
    )
    for result in results:
        assert result.error == "" and result.success, result
        assert result.task_measures["max_reward"] == 1.0
    env = PUSHT.make_env(env_args)
    held = run_episode(PUSHT, env, _Hold(), 100000, OBS_KEYS, 2, 5, render_camera="top")
    assert held.steps == 5 and not held.success and held.error == ""
    assert 0.0 <= held.task_measures["max_reward"] < 1.0
    assert len(held.frames) == 5 and held.frames[0].shape == (256, 256, 3) and held.frames[0].dtype == np.uint8


class _Hold:
    """Targets the agent's own position: nothing moves."""

    def reset(self, env, seed: int) -> None:
        pass

    def act(self, observation_history, env):
        return observation_history[-1:, -2:], None


def test_a_push_t_file_with_7_d_actions_or_an_arm_file_named_for_push_t_is_refused_in_one_line(tmp_path):
    rng = np.random.default_rng(0)
    episode = make_episode(12, rng)
    episode.obs = {"block_keypoints": rng.uniform(0, 512, (12, 18)), "agent_pos": rng.uniform(0, 512, (12, 2))}
    seven_d = tmp_path / "pusht_7d.hdf5"
    write_demonstrations(seven_d, [episode], PUSHT.make_env_args("absolute"), file_attrs={})
    with pytest.raises(DatasetError) as error:
        ingest_demonstrations(seven_d, tmp_path / "a", OBS_KEYS, env_name=ENV_NAME)
    assert str(error.value).startswith(f"{seven_d}: demo 'demo_0'") and "expected width 2" in str(error.value)
    assert "\n" not in str(error.value) and not (tmp_path / "a").exists()

    arm = tmp_path / "lift.hdf5"
    write_demonstrations(arm, [make_episode(12, rng)], get_task("lift").make_env_args("absolute"), file_attrs={})
    with pytest.raises(DatasetError) as error:
        ingest_demonstrations(arm, tmp_path / "b", OBS_KEYS, env_name=ENV_NAME)
    assert str(error.value) == (
        f"{arm}: data.attrs['env_args'] env_name='Lift': this task's demos come from 'gym_pusht/PushT-v0'"
    )
    assert not (tmp_path / "b").exists()
