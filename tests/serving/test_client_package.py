"""The client package installed on its own, with numpy 2, in a fresh virtual environment, drives a server."""

import json
import os
import shutil
import subprocess
import venv

import numpy as np
import pytest

from tests.serving.conftest import CLIENT_DIR, in_process_chunks, observations

ROBOT_SCRIPT = """
import json, sys
import numpy as np
from carp_client import PolicyClient

url, episode = sys.argv[1], np.array(json.loads(sys.argv[2]), dtype=np.float32)
with PolicyClient(url, timeout=30) as client:
    keys = list(client.metadata["observation_keys"])
    client.reset(seed=5)
    replies = [client.infer({"object": obs[:1], "robot0_eef_pos": obs[1:]}) for obs in episode]
print(json.dumps({
    "numpy": np.__version__,
    "keys": keys,
    "actions": [reply["actions"].tolist() for reply in replies],
    "dtypes": sorted({str(reply["actions"].dtype) for reply in replies}),
    "heavy_modules": sorted(name for name in ("torch", "carp", "onnxruntime") if name in sys.modules),
    "client_file": sys.modules["carp_client"].__file__,
}))
"""


def pip(environment, *arguments: str) -> subprocess.CompletedProcess:
    python = environment / "bin" / "python"
    command = [str(python), "-m", "pip", "install", "--quiet", *arguments]
    return subprocess.run(command, capture_output=True, text=True, timeout=600, env=clean_env())


def clean_env() -> dict[str, str]:
    """The process's environment without carp's paths, so that nothing of carp's environment leaks in."""
    return {key: value for key, value in os.environ.items() if key not in ("PYTHONPATH", "VIRTUAL_ENV")}


@pytest.mark.slow
def test_the_client_package_from_a_fresh_numpy_2_environment_gets_the_served_chunks(server, reference_policy, tmp_path):
    environment = tmp_path / "robot-venv"
    venv.EnvBuilder(with_pip=True).create(environment)
    numpy_2 = pip(environment, "numpy>=2")
    if numpy_2.returncode != 0:
        pytest.skip(f"no package registry reachable for numpy>=2 (pip said: {numpy_2.stderr.strip()[-300:]})")
    # Built from a copy: setuptools writes its build directory beside the sources.
    sources = shutil.copytree(CLIENT_DIR, tmp_path / "client", ignore=shutil.ignore_patterns("build", "*.egg-info"))
    installed = pip(environment, str(sources))
    assert installed.returncode == 0, installed.stderr[-2000:]

    episode = observations(4, seed=11)
    completed = subprocess.run(
        [str(environment / "bin" / "python"), "-c", ROBOT_SCRIPT, server.url, json.dumps(np.stack(episode).tolist())],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,  # not the repository, whose clients/python must not shadow the installed package
        env=clean_env(),
    )
    assert completed.returncode == 0, completed.stderr[-2000:]
    robot = json.loads(completed.stdout.strip().splitlines()[-1])
    assert int(robot["numpy"].split(".")[0]) >= 2
    assert robot["heavy_modules"] == [] and str(environment) in robot["client_file"]
    assert robot["keys"] == ["object", "robot0_eef_pos"] and robot["dtypes"] == ["float32"]
    # float32 values survive the JSON round trip exactly (each float32 is a float64 that prints and parses back).
    served = np.array(robot["actions"], dtype=np.float32)
    np.testing.assert_array_equal(served, np.stack(in_process_chunks(reference_policy, episode, seed=5)))
