"""A tiny served CARP policy (the policy tests' factory), its spec, and the in-process reference it must match."""

import sys
from collections import deque
from pathlib import Path

import numpy as np
import pytest
import torch

from carp.policies.registry import load_policy
from carp.serving.model import ModelSource, ServedModel, file_sha256
from carp.serving.server import PolicyServer, ServerSettings, ServerThread
from carp.serving.session import ServingSpec
from tests.policies.carp.factories import OBS_DIM, OBS_STEPS, tiny_policy

# The robot-side client is its own package (clients/python), not installed in carp's environment.
CLIENT_DIR = Path(__file__).resolve().parents[2] / "clients" / "python"
if str(CLIENT_DIR) not in sys.path:
    sys.path.insert(0, str(CLIENT_DIR))

INFERENCE = {"top_k": 8}
"""Sampling among 8 tokens, so the per-episode generator matters and a wrong seed or history shows."""

SPEC = ServingSpec(
    obs_keys=("object", "robot0_eef_pos"),
    obs_steps=OBS_STEPS,
    obs_dim=OBS_DIM,
    action_horizon=8,
    action_dim=2,
    action_steps=4,
    control_period_s=0.05,  # Lift's 20 Hz
    obs_widths=(1, 2),
)
PROTOCOL = {
    "format": 1,
    "observations": "state",
    "obs_keys": ["object", "robot0_eef_pos"],
    "obs_widths": [1, 2],
    "obs_steps": OBS_STEPS,
    "action_horizon": 8,
    "action_steps": 4,
    "cameras": [],
    "image_size": None,
}
"""What training records for :data:`SPEC` (`carp.serving.protocol`)."""
MAX_REQUEST_BYTES = 4096


def save_tiny_checkpoint(path: Path, seed: int = 0, **metadata) -> Path:
    """The tiny CARP policy of `seed` saved at `path`, trained on lift as far as its metadata says, with `metadata`."""
    policy = tiny_policy(seed=seed)
    policy.metadata.update({"task": "lift", "serving": PROTOCOL} | metadata)
    policy.save(path)
    return path


@pytest.fixture(scope="package")
def checkpoint(tmp_path_factory) -> Path:
    return save_tiny_checkpoint(tmp_path_factory.mktemp("serving") / "policy.pt")


def served_model(checkpoint: Path) -> ServedModel:
    policy = load_policy(checkpoint)
    policy.configure_inference(**INFERENCE)
    return ServedModel(policy, ModelSource(str(checkpoint), file_sha256(checkpoint)), dict(INFERENCE))


def start_server(checkpoint: Path, **settings) -> ServerThread:
    settings = {"port": 0, "max_request_bytes": MAX_REQUEST_BYTES} | settings
    return ServerThread(PolicyServer(served_model(checkpoint), SPEC, ServerSettings(**settings))).start()


@pytest.fixture(scope="package")
def server(checkpoint):
    # Built before the per-test one-thread setting applies, and a server built and warmed up under another thread
    # count computes chunks that differ from the one-thread in-process references in the last bits.
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        running = start_server(checkpoint)
    finally:
        torch.set_num_threads(previous)
    yield running
    running.stop()


@pytest.fixture(scope="package")
def reference_policy(checkpoint):
    policy = load_policy(checkpoint)
    policy.configure_inference(**INFERENCE)
    return policy


def observations(steps: int, seed: int) -> list[np.ndarray]:
    """`steps` random (Do,) float32 observations."""
    rng = np.random.default_rng(seed)
    return [rng.normal(size=OBS_DIM).astype(np.float32) for _ in range(steps)]


def in_process_chunks(policy, episode: list[np.ndarray], seed: int) -> list[np.ndarray]:
    """(H, A) chunks an in-process rollout predicts: first observation repeated `To` times, generator per episode."""
    generator = torch.Generator()
    generator.manual_seed(seed)
    history = deque([episode[0]] * OBS_STEPS, maxlen=OBS_STEPS)
    chunks = []
    for index, obs in enumerate(episode):
        if index:
            history.append(obs)
        chunks.append(policy.predict_action_timed(np.stack(history)[None], generator=generator).actions[0])
    return chunks
