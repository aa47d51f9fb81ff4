"""The scripted Push-T expert: its push library's invariance to the block's pose, transits that keep off the T,
determinism for a seed, and (slow) success on fixed seeds within the step limit."""

import math

import numpy as np
import pytest

from carp.tasks.pusht import env as pusht
from carp.tasks.pusht import expert as pusht_expert

# Poses well inside the workspace, where no wall is in reach of a library push.
POSES_AWAY_FROM_WALLS = [(200.0, 300.0, 1.1), (300.0, 220.0, -2.4), (256.0, 256.0, math.pi)]


@pytest.fixture(scope="module")
def library():
    return pusht_expert.push_library()


@pytest.fixture(scope="module")
def scratch():
    return pusht_expert.ScratchSimulation()


def test_goal_pose_has_no_error_and_composition_moves_in_the_block_frame():
    assert pusht_expert.pose_error(np.asarray(pusht.GOAL_POSE)) == pytest.approx(0.0, abs=1e-9)
    # A step of 10 along the block's x axis, with the block turned a quarter turn, moves it along the workspace's y.
    moved = pusht_expert.compose(np.array([[100.0, 100.0, math.pi / 2]]), np.array([[10.0, 0.0, 0.1]]))[0, 0]
    np.testing.assert_allclose(moved, [100.0, 110.0, math.pi / 2 + 0.1], atol=1e-9)


def test_library_covers_every_edge_and_moves_the_block(library):
    assert len(library) > 200
    starts = np.array([push.targets[0] for push in library])
    clearance = pusht_expert.distance_to_t(starts)
    assert clearance.min() > pusht_expert.AGENT_RADIUS  # every push starts with the disc off the T
    # Starts all round the T: above the crossbar, below it, beside both ends and the stem, below the foot.
    assert starts[:, 1].min() < -15 and starts[:, 1].max() > 135
    assert starts[:, 0].min() < -75 and starts[:, 0].max() > 75
    displacements = np.array([push.displacement for push in library])
    assert np.abs(displacements).max(axis=1).min() > 1e-3


@pytest.mark.parametrize("pose", POSES_AWAY_FROM_WALLS)
def test_a_push_moves_the_block_by_its_library_displacement_from_any_pose(library, scratch, pose):
    block_pose = np.asarray(pose)
    for push in library[::37]:
        targets = pusht_expert.to_workspace(block_pose, push.targets)
        scratch.place(targets[0], block_pose)
        for target in targets[1:]:
            scratch.drive(target)
        predicted = pusht_expert.compose(block_pose[None], push.displacement[None])[0, 0]
        reached = scratch.block_pose()
        # Rotated, the same push differs only by floating-point rounding through the contact solver.
        np.testing.assert_allclose(reached[:2], predicted[:2], atol=0.05)
        assert reached[2] == pytest.approx(predicted[2], abs=1e-3)


@pytest.mark.parametrize("pose", POSES_AWAY_FROM_WALLS)
def test_transit_to_the_far_side_keeps_off_the_t(library, scratch, pose):
    block_pose = np.asarray(pose)
    center = pusht_expert.to_workspace(block_pose, pusht_expert.T_CENTER)
    for push in library[::23]:
        start = pusht_expert.to_workspace(block_pose, push.targets[0])
        agent = 2 * center - start  # opposite the push's start, across the T
        agent = center + (agent - center) / np.linalg.norm(agent - center) * 110.0
        waypoints = pusht_expert.transit_waypoints(agent, block_pose, start)
        np.testing.assert_allclose(waypoints[-1], start)
        scratch.place(agent, block_pose)
        for waypoint in waypoints:
            scratch.drive(waypoint)
        # The simulated agent, lagging behind its targets, still never touched the block.
        np.testing.assert_array_equal(scratch.block_pose(), block_pose)


def test_same_expert_seed_gives_the_same_actions_and_another_seed_other_ones():
    environment = pusht.PushTEnv(render_size=96)
    runs = []
    for expert_seed in (0, 0, 1):
        environment.reset(1002)  # a short episode (about 50 steps) for expert seed 0
        expert = pusht_expert.PushTExpert(seed=expert_seed)
        actions = []
        for _ in range(60):
            actions.append(expert.act(environment))
            if environment.step(actions[-1]).done:
                break
        runs.append(np.array(actions))
    environment.close()
    np.testing.assert_array_equal(runs[0], runs[1])
    # Another tie-breaking seed leads to other, equally good pushes.
    assert runs[0].shape != runs[2].shape or not np.array_equal(runs[0], runs[2])


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1000, 1001, 1002])
def test_expert_succeeds_within_the_step_limit(seed):
    environment = pusht.PushTEnv(render_size=96)
    success, steps = pusht_expert.run_episode(environment, seed)
    environment.close()
    assert success and steps <= pusht.MAX_STEPS


def test_the_expert_backs_off_a_t_it_starts_against():
    # DP's reset for seed 50 draws the agent against the T's crossbar: no push can start from there.
    environment = pusht.PushTEnv(render_size=96)
    environment.reset(50)
    state = environment.state()
    environment.close()
    agent, centre = state[:2], pusht_expert.to_workspace(state[2:], pusht_expert.T_CENTER)
    target = pusht_expert._retreat_target(state)
    assert np.linalg.norm(target - agent) == pytest.approx(pusht_expert.RETREAT_DISTANCE)
    assert np.linalg.norm(target - centre) > np.linalg.norm(agent - centre) + 29.0
    corner = np.array([20.0, 20.0, *state[2:]])  # in a corner, backing off stays inside the workspace
    assert np.all(pusht_expert._retreat_target(corner) >= pusht_expert.AGENT_RADIUS)


@pytest.mark.slow
def test_expert_succeeds_from_a_start_against_the_t():
    environment = pusht.PushTEnv(render_size=96)
    success, steps = pusht_expert.run_episode(environment, 50, expert_seed=50)
    environment.close()
    assert success and steps <= pusht.MAX_STEPS
