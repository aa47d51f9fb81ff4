"""Training on several processes: batch shares and their loss weights, and real torchrun runs of the shared loop.

The torchrun tests start `distributed_worker.py` (a tiny policy on 97 random windows in batches of 16, so that the
last batch of every epoch leaves one of two processes without a window) on two CPU processes with gloo:

- next-token (a loss without random draws): two processes follow the one-process loss curve and end with its weights
  up to the order of float32 sums (losses within 1e-5 relative, weights within 1e-5 absolute; float32 has 24 bits);
- Diffusion Policy's transformer (noise, steps and dropout drawn in every process): a run killed with SIGKILL after
  its second training state resumes on two processes and ends with exactly the uninterrupted run's weights; killing
  the launcher takes its processes down too;
- rank 0 alone has epochs reported to it;
- a process that fails makes the launcher (`run_processes`) fail with one line naming its rank and exit code.
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from carp.training.distributed import Processes, batch_share, cpu_threads_per_process, describe_failures, seed_epoch

WORKER = Path(__file__).with_name("distributed_worker.py")
REPO = Path(__file__).resolve().parents[2]


def _command(processes: int, *arguments: str) -> list[str]:
    if processes == 1:
        return [sys.executable, str(WORKER), *arguments]
    return [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={processes}",
            str(WORKER), *arguments]  # fmt: skip


def _environment() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}


def _train(processes: int, family: str, directory: Path, *options: str) -> subprocess.CompletedProcess:
    arguments = (family, str(directory / "out"), str(directory / "checkpoints"), *options)
    completed = subprocess.run(
        _command(processes, *arguments), env=_environment(), capture_output=True, text=True, timeout=600
    )
    assert completed.returncode == 0, completed.stderr[-3000:]
    return completed


def _reported(directory: Path, rank: int) -> list[dict]:
    return json.loads((directory / "out" / f"rank{rank}.json").read_text())["reported"]


def _weights(directory: Path) -> dict[str, torch.Tensor]:
    return torch.load(directory / "out" / "policy.pt", weights_only=True)


@pytest.mark.parametrize("world_size", [2, 3])
@pytest.mark.parametrize("batch_size", [1, 2, 5, 16])
def test_batch_shares_cover_the_batch_and_their_weighted_means_average_to_its_mean(world_size, batch_size):
    indices = torch.randperm(40)[:batch_size]
    losses = torch.rand(40, dtype=torch.float64)
    shares = [batch_share(indices, Processes(rank, world_size)) for rank in range(world_size)]
    kept = [share for share, weight in shares if weight > 0]
    assert torch.equal(torch.cat(kept), indices)
    assert max(len(share) for share in kept) - min(len(share) for share in kept) <= 1
    assert all(len(share) == 1 for share, weight in shares if weight == 0)
    average = sum(weight * losses[share].mean() for share, weight in shares) / world_size
    assert float(average) == pytest.approx(float(losses[indices].mean()), rel=1e-12)


def test_one_process_trains_on_the_whole_batch_with_unit_weight():
    indices = torch.arange(7)
    share, weight = batch_share(indices, Processes())
    assert share is indices and weight == 1.0


def test_each_process_draws_its_own_reproducible_noise_per_epoch():
    def draw(rank: int, epoch: int) -> torch.Tensor:
        seed_epoch(5, epoch, Processes(rank, 2))
        return torch.rand(4)

    assert torch.equal(draw(1, 3), draw(1, 3))
    assert not torch.equal(draw(0, 3), draw(1, 3)) and not torch.equal(draw(1, 3), draw(1, 4))
    before = torch.get_rng_state()
    seed_epoch(5, 3, Processes())
    assert torch.equal(torch.get_rng_state(), before)


@pytest.mark.parametrize(
    ("exit_codes", "described"),
    [
        ({1: 3, 0: -signal.SIGTERM}, "rank 1 exit code 3"),
        ({1: 3}, "rank 1 exit code 3"),
        ({2: 1, 0: -signal.SIGKILL, 1: -signal.SIGTERM}, "rank 0 exit code -9, rank 2 exit code 1"),
        ({1: -signal.SIGTERM, 0: -signal.SIGTERM}, "rank 0 exit code -15, rank 1 exit code -15"),
    ],
)
def test_failures_name_the_ranks_that_failed_not_those_the_launcher_stopped(exit_codes, described):
    assert describe_failures(exit_codes) == described


def test_processes_share_the_cores():
    cores = len(os.sched_getaffinity(0))
    assert cpu_threads_per_process(1) == cores
    assert cpu_threads_per_process(cores + 1) == 1


@pytest.mark.slow
def test_two_processes_follow_the_one_process_loss_curve_and_only_rank_0_reports(tmp_path):
    _train(1, "next_token", tmp_path / "one")
    _train(2, "next_token", tmp_path / "two")
    one, two = _reported(tmp_path / "one", 0), _reported(tmp_path / "two", 0)
    assert [epoch["epoch"] for epoch in two] == [0, 1, 2, 3]
    for single, shared in zip(one, two, strict=True):
        assert shared["loss"] == pytest.approx(single["loss"], rel=1e-5)
        assert shared["learning_rate"] == pytest.approx(single["learning_rate"], rel=1e-12)
    assert one[-1]["loss"] < one[0]["loss"] - 0.05  # it learns, so the curves compare more than a constant
    single_weights, shared_weights = _weights(tmp_path / "one"), _weights(tmp_path / "two")
    assert single_weights.keys() == shared_weights.keys()
    for name, value in single_weights.items():
        torch.testing.assert_close(shared_weights[name], value, rtol=0, atol=1e-5, msg=name)
    assert _reported(tmp_path / "two", 1) == []
    assert json.loads((tmp_path / "two" / "out" / "rank1.json").read_text())["world_size"] == 2


@pytest.mark.slow
def test_carp_on_two_processes_follows_the_one_process_losses_and_token_accuracies(tmp_path):
    _train(1, "carp", tmp_path / "one")
    _train(2, "carp", tmp_path / "two")
    one, two = _reported(tmp_path / "one", 0), _reported(tmp_path / "two", 0)
    assert [epoch["epoch"] for epoch in two] == [0, 1, 2, 3]
    accuracies = [key for key in one[0] if key.startswith("token_accuracy")]
    assert accuracies == ["token_accuracy", "token_accuracy_scale_1", "token_accuracy_scale_2"]
    for single, shared in zip(one, two, strict=True):
        assert shared["loss"] == pytest.approx(single["loss"], rel=1e-5)
        # The accuracy sums of both shares are added: the same counts, up to a near-tie that rounding may flip
        # (one token of 582 is 0.0017).
        for key in accuracies:
            assert 0.0 <= shared[key] <= 1.0
            assert shared[key] == pytest.approx(single[key], abs=0.004), key
    assert one[-1]["loss"] < one[0]["loss"] - 0.05
    single_weights, shared_weights = _weights(tmp_path / "one"), _weights(tmp_path / "two")
    for name, value in single_weights.items():
        torch.testing.assert_close(shared_weights[name], value, rtol=0, atol=1e-5, msg=name)


def _wait_for(condition, what: str, seconds: float = 300) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.05)


def _alive(pid: int) -> bool:
    try:
        status = Path(f"/proc/{pid}/stat").read_text().split(") ")[-1].split()[0]
    except FileNotFoundError:
        return False
    return status != "Z"


@pytest.mark.slow
def test_a_killed_two_process_run_resumes_on_two_processes_to_the_uninterrupted_weights(tmp_path):
    _train(2, "diffusion_transformer", tmp_path / "uninterrupted")
    run = tmp_path / "interrupted"
    options = ("diffusion_transformer", str(run / "out"), str(run / "checkpoints"))
    with (tmp_path / "killed.log").open("w") as log:
        launcher = subprocess.Popen(
            _command(2, *options, "--pause-after-epoch", "2"),
            env=_environment(),
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        _wait_for(lambda: (run / "out" / "paused").exists() or launcher.poll() is not None, "never paused")
        assert launcher.poll() is None, (tmp_path / "killed.log").read_text()[-3000:]
        pids = [int((run / "out" / f"rank{rank}.pid").read_text()) for rank in range(2)]
        os.killpg(launcher.pid, signal.SIGKILL)
        launcher.wait(timeout=60)
    # torchrun starts its processes in sessions of their own; they end with their launcher.
    _wait_for(lambda: not any(_alive(pid) for pid in pids), "a training process outlived its launcher", 30)
    state = torch.load(run / "checkpoints" / "training_state.pt", weights_only=False)
    assert state["epoch"] == 2 and state["metadata"]["loop"]["processes"] == 2

    resumed = _train(2, "diffusion_transformer", run)
    assert "resuming diffusion_transformer training from" in resumed.stderr
    assert "diffusion_transformer epoch 1/4" not in resumed.stderr
    expected, actual = _weights(tmp_path / "uninterrupted"), _weights(run)
    assert expected.keys() == actual.keys()
    for name, value in expected.items():
        assert torch.equal(actual[name], value), name
    reference = _reported(tmp_path / "uninterrupted", 0)
    assert [epoch["loss"] for epoch in _reported(run, 0)] == [epoch["loss"] for epoch in reference]


@pytest.mark.slow
def test_a_failed_process_makes_the_launcher_fail_with_one_line_naming_it(tmp_path):
    script = tmp_path / "fails_on_rank_1.py"
    script.write_text("import os, sys\nsys.exit(3 if os.environ['RANK'] == '1' else 0)\n")
    launcher = (
        "import sys\n"
        "from pathlib import Path\n"
        "from carp.training.distributed import ProcessesFailed, run_processes\n"
        "try:\n"
        f"    run_processes(Path({str(script)!r}), ['--flag'], 2)\n"
        "except ProcessesFailed as error:\n"
        "    print(error)\n"
        "    sys.exit(1)\n"
    )
    completed = subprocess.run(
        [sys.executable, "-c", launcher], env=_environment(), capture_output=True, text=True, timeout=300
    )
    assert completed.returncode == 1, completed.stderr[-3000:]
    assert completed.stdout.strip() == "fails_on_rank_1.py on 2 processes failed (rank 1 exit code 3)"
