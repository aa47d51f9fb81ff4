"""Scale schedules of the paper's Fig. 10 train, evaluate, export and serve through the real pipeline (every one of
the five exports and matches PyTorch in tests/policies/carp/test_onnx_policy.py).

A copy of the shared arm pipeline (its demos stand) runs `dvc repro` with `scales: [1]` (a single scale, below the
encoder's latent length of 4), then `dvc exp run -S scales=...` for three scales (the last below the latent length)
and six (a latent longer than the encoder's, resampled to the last scale): the three cases of the latent's length.
After each, the evaluated CARP policy is served on the ONNX Runtime backend and its chunk compared with the
in-process prediction.
"""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from carp.config import load_params
from carp.policies.registry import load_policy
from carp.serving.server import PolicyServer, ServerSettings, ServerThread
from carp.serving.startup import load_served_model
from tests.pipeline.shared_workspaces import copy_pipeline
from tests.pipeline.workspace import dvc, run

pytestmark = pytest.mark.slow

CLIENT_DIR = Path(__file__).resolve().parents[2] / "clients" / "python"
if str(CLIENT_DIR) not in sys.path:
    sys.path.insert(0, str(CLIENT_DIR))

SCHEDULES = ([1], [1, 2, 3], [1, 2, 3, 4, 5, 6])


def served_and_in_process(workspace, checkpoint, seed: int) -> tuple[np.ndarray, np.ndarray, str]:
    """The chunk `carp serve` answers to one observation through the robot-side client, the chunk its policy predicts
    in process for the same history (the first observation repeated To times), and the backend that ran."""
    from carp_client import PolicyClient

    params = load_params(workspace / "params.yaml")
    served, spec = load_served_model(checkpoint, params, backend="onnxruntime")
    obs = np.random.default_rng(seed).normal(size=spec.obs_dim).astype(np.float32)
    with torch.inference_mode():
        expected = served.policy.predict_action(np.repeat(obs[None, None], spec.obs_steps, axis=1))[0]
    thread = ServerThread(PolicyServer(served, spec, ServerSettings(port=0))).start()
    try:
        with PolicyClient(thread.url, timeout=30, connect_attempts=20, initial_backoff_s=0.05) as client:
            return client.infer({"obs": obs})["actions"], expected, served.backend
    finally:
        thread.stop()


def test_a_schedule_per_latent_length_trains_evaluates_exports_and_serves(lift_pipeline, tmp_path):
    workspace = copy_pipeline(lift_pipeline, tmp_path, {"scales": SCHEDULES[0], "policies": ["carp"]})
    for index, schedule in enumerate(SCHEDULES):
        command = (
            [sys.executable, "-m", "dvc", "repro"] if index == 0 else dvc("exp", "run", "-S", f"scales={schedule}")
        )
        completed = run(command, workspace)
        assert completed.returncode == 0, (schedule, completed.stderr[-3000:])
        assert (workspace / "reports/eval/lift/carp/seed0.json").exists(), schedule
        checkpoint = workspace / "models/policy/lift/carp/seed0/policy.pt"
        policy = load_policy(checkpoint)
        spec = policy.tokenizer.spec
        assert list(spec.scales) == schedule and spec.latent_length == max(4, schedule[-1])
        assert policy.spec.sequence_length == policy.spec.action_dim * sum(schedule)
        served, expected, backend = served_and_in_process(workspace, checkpoint, index)
        assert backend == "onnxruntime"
        assert served.shape == (spec.action_horizon, spec.action_dim) and np.all(np.isfinite(served))
        np.testing.assert_allclose(served, expected, rtol=1e-5, atol=1e-5)
