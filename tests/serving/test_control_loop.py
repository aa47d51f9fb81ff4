"""The example control loop (`examples/serve_control_loop.py`) against carp's Lift simulator and its evaluation."""

import importlib.util

import numpy as np
import pytest

from carp.config import DataConfig, Params
from carp.policies.carp.config import CarpInference
from carp.serving.protocol import SERVING_METADATA_KEY
from carp.tasks import get_task
from tests.serving.conftest import CLIENT_DIR
from tests.serving.random_policy import LIFT_OBS_WIDTHS, random_lift_policy

EXAMPLE = CLIENT_DIR.parents[1] / "examples" / "serve_control_loop.py"
SEEDS, MAX_STEPS = (100000, 100001), 24


def load_example():
    spec = importlib.util.spec_from_file_location("serve_control_loop", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_the_served_loop_executes_the_in_process_evaluations_actions_bit_for_bit(tmp_path):
    example = load_example()
    checkpoint = tmp_path / "policy.pt"
    random_lift_policy(tiny=True).save(checkpoint)  # To = 2, H = 8, Ta = 4
    # Draws among 3 tokens, so the per-episode seeding on both sides is part of what is compared.
    server, model, spec = example.start_server(checkpoint, Params(inference={"carp": CarpInference(top_k=3)}))
    task = get_task("lift")
    action_format = task.action_format("absolute")
    env = task.make_env(task.make_env_args("absolute"))
    try:
        with example.PolicyClient(server.url, timeout=30) as client:
            scheduler = example.ChunkScheduler.from_metadata(client.metadata)
            served = [
                example.run_served_episode(client, scheduler, task, env, seed, action_format, MAX_STEPS)
                for seed in SEEDS
            ]
        in_process = [
            example.in_process_episode(checkpoint, model.inference, task, env, seed, spec, action_format, MAX_STEPS)
            for seed in SEEDS
        ]
    finally:
        env.close()
        server.stop()
    for episode, (actions, success) in zip(served, in_process, strict=True):
        assert episode.actions.shape == actions.shape == (MAX_STEPS, 7)
        np.testing.assert_array_equal(episode.actions, actions)
        assert episode.success == success
        assert episode.chunks == MAX_STEPS // spec.action_steps
    assert not np.array_equal(served[0].actions, served[1].actions)


@pytest.mark.slow
def test_a_checkpoint_without_its_protocol_is_driven_with_the_concatenated_obs(tmp_path):
    # The default size, whose H = 16 and Ta = 8 are the params' defaults, from which the old checkpoint's spec comes.
    example = load_example()
    policy = random_lift_policy(tiny=False)
    recorded, old = tmp_path / "recorded.pt", tmp_path / "old.pt"
    policy.save(recorded)
    del policy.metadata[SERVING_METADATA_KEY]
    policy.save(old)
    task = get_task("lift")
    action_format = task.action_format("absolute")
    env = task.make_env(task.make_env_args("absolute"))
    runs = []
    try:
        for checkpoint, params in ((recorded, None), (old, Params(data=DataConfig(obs_keys=tuple(LIFT_OBS_WIDTHS))))):
            server, _, spec = example.start_server(checkpoint, params)
            try:
                with example.PolicyClient(server.url, timeout=30) as client:
                    assert bool(client.metadata["observation_keys"]) == (params is None)
                    scheduler = example.ChunkScheduler.from_metadata(client.metadata)
                    runs.append(example.run_served_episode(client, scheduler, task, env, SEEDS[0], action_format, 16))
            finally:
                server.stop()
    finally:
        env.close()
    assert runs[0].chunks == runs[1].chunks == 16 // spec.action_steps
    np.testing.assert_array_equal(runs[0].actions, runs[1].actions)
