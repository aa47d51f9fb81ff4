"""Task measures: Square's insertion offset at the nut's first contact with its peg, and the rollout carrying it."""

import numpy as np
import pytest

from carp import simulation
from carp.evaluation.rollout import EpisodeResult, run_episode
from carp.evaluation.runner import episodes_table, measure_summary
from carp.evaluation.sources import ExpertSource
from carp.evaluation.task_measures import InsertionOffset, NoMeasure, measure_for

OBS_KEYS = ("object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")


@pytest.fixture(scope="module")
def square_env():
    env = simulation.make_env(simulation.make_env_args("square"))
    yield env
    env.close()


def _drop_nut(env, offset_m: float, steps: int = 200) -> InsertionOffset:
    """Hold the nut 2 cm above the peg's top, `offset_m` off its centre along x, let it fall and watch."""
    simulation.reset_env(env, 100_000)
    nut = env.nuts[env.nut_id]
    peg = env.sim.data.body_xpos[env.peg1_body_id].copy()
    peg_top = max(
        env.sim.data.geom_xpos[geom][2] + env.sim.model.geom_size[geom][2]
        for geom in np.flatnonzero(env.sim.model.geom_bodyid == env.peg1_body_id)
    )
    qpos = env.sim.data.get_joint_qpos(nut.joints[0]).copy()
    qpos[:3] = [peg[0] + offset_m, peg[1], peg_top + 0.02]
    env.sim.data.set_joint_qpos(nut.joints[0], qpos)
    env.sim.forward()
    measure = measure_for(env)
    measure.reset(env)
    for step in range(1, steps + 1):
        env.sim.step()
        measure.observe(env, step)
    return measure


@pytest.mark.slow
def test_a_nut_dropped_onto_its_peg_is_measured_at_its_offset_on_first_contact(square_env):
    assert isinstance(measure_for(square_env), InsertionOffset)
    values = _drop_nut(square_env, offset_m=0.006).values()
    # The nut falls straight down until it touches the peg, so its offset then is the one it was dropped with; a
    # millimetre allows for the fall's drift before contact.
    assert values["insertion_offset_mm"] == pytest.approx(6.0, abs=1.0)
    assert 1 <= values["insertion_contact_step"] < 200
    # Dropped far beside the peg, the nut never touches it: no measure.
    missed = _drop_nut(square_env, offset_m=0.2).values()
    assert np.isnan(missed["insertion_offset_mm"]) and np.isnan(missed["insertion_contact_step"])


@pytest.mark.slow
def test_the_scripted_expert_puts_the_nut_on_within_robosuites_on_peg_tolerance(square_env):
    result = run_episode(square_env, ExpertSource("square"), 1000, OBS_KEYS, 2, 400)
    assert result.success
    assert 0 <= result.task_measures["insertion_offset_mm"] < 30.0  # robosuite's on-peg check: 3 cm in x and y
    assert 0 < result.task_measures["insertion_contact_step"] <= result.steps


def test_tasks_without_a_measure_add_no_columns_and_measures_summarize_over_measured_episodes():
    assert NoMeasure().values() == {}
    plain = [EpisodeResult(seed, True, 50, 1.0) for seed in (1, 2)]
    assert "insertion_offset_mm" not in episodes_table(plain) and measure_summary(plain) == {}
    measured = [
        EpisodeResult(1, True, 50, 1.0, task_measures={"insertion_offset_mm": 4.0, "insertion_contact_step": 30.0}),
        EpisodeResult(2, True, 60, 1.0, task_measures={"insertion_offset_mm": 6.0, "insertion_contact_step": 35.0}),
        EpisodeResult(
            3, False, 400, 1.0, task_measures={"insertion_offset_mm": np.nan, "insertion_contact_step": np.nan}
        ),
    ]
    table = episodes_table(measured)
    assert table["insertion_offset_mm"].tolist()[:2] == [4.0, 6.0] and np.isnan(table["insertion_offset_mm"][2])
    summary = measure_summary(measured)
    assert summary["insertion_offset_mm_mean"] == 5.0 and summary["insertion_offset_mm_variance"] == 2.0
    assert summary["insertion_offset_mm_episodes"] == 2
