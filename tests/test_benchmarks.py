"""`make benchmark`'s scripts run end to end on tiny settings and print tables whose numbers agree with each other.

Speeds are not asserted here (they depend on the machine; docs/benchmarks.md states the measured ones); what is asserted
is that the scripts still run against the current library, print every row, and refuse bad arguments with one line.
"""

import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
NUMBER = r"(\d+(?:\.\d+)?)"


def run_benchmark(script: str, *arguments: str, timeout: float = 300) -> subprocess.CompletedProcess:
    # Short OpenMP spinning, as in dvc.yaml's training stages: `make test` runs two test processes on two cores, and
    # the benchmark's two-thread training steps, spinning at full length against the other process, slow down many
    # times over.
    return subprocess.run(
        [sys.executable, f"benchmarks/{script}", *arguments],
        cwd=REPO_ROOT,
        env={**os.environ, "GOMP_SPINCOUNT": "5000"},
        capture_output=True,
        text=True,
        timeout=timeout,
    )


@pytest.mark.slow
def test_tokenizer_throughput_prints_every_variant_with_consistent_numbers():
    completed = run_benchmark(
        "tokenizer_throughput.py",
        *("--episodes", "3", "--rounds", "2", "--block", "2", "--device", "cpu"),
    )
    assert completed.returncode == 0, completed.stderr[-2000:]
    header = completed.stdout.splitlines()[0]
    windows = int(re.search(r"(\d+) windows", header).group(1))
    assert (
        "A=10" in header
        and re.search(r"\bcpu [A-Z0-9]+\b", header)
        and "median of 2 epochs" in header
        and "turns of 2 batches" in header
    )
    variants = ("vectorized (one module)", "loop over 10 modules")
    row_pattern = rf"^({'|'.join(map(re.escape, variants))})\s+{NUMBER}\s+{NUMBER}\s+{NUMBER}x$"
    rows = {
        match.group(1): tuple(float(value) for value in match.groups()[1:])
        for match in re.finditer(row_pattern, completed.stdout, flags=re.MULTILINE)
    }
    assert tuple(rows) == variants, completed.stdout
    (_, vectorized_rate, speed_up), (_, loop_rate, loop_speed_up) = rows.values()
    assert loop_speed_up == 1.0
    for seconds, rate, _ in rows.values():
        assert seconds > 0
        assert rate == pytest.approx(windows / seconds, rel=0.06)  # seconds are printed to 0.01 s
    # The speed-up is printed to 0.01, the rates to whole windows/s (a tiny run's rates are small).
    assert speed_up == pytest.approx(vectorized_rate / loop_rate, rel=0.01, abs=0.006)
    low, high, median = (
        float(value)
        for value in re.search(rf"single rounds: {NUMBER}x to {NUMBER}x, median {NUMBER}x", completed.stdout).groups()
    )
    assert low <= median <= high
    # The ratio is a figure of this machine and batch size, not a pass/fail line.
    assert "target" not in completed.stdout


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (("--rounds", "0"), "--rounds must be at least 1, got 0"),
        (("--block", "-1"), "--block must be 0 (whole epochs) or a positive number of batches, got -1"),
        (("--device", "gpu0"), '--device must be "auto", "cpu", "cuda" or "cuda:<index>", got \'gpu0\''),
    ],
)
def test_tokenizer_throughput_refuses_bad_arguments_in_one_line(arguments, message):
    completed = run_benchmark("tokenizer_throughput.py", *arguments, timeout=120)
    assert completed.returncode == 2
    assert completed.stderr.strip().splitlines()[-1] == f"tokenizer_throughput.py: error: {message}"
    assert completed.stdout == ""


def test_sweep_workers_refuses_a_worker_count_below_one():
    # Its measurement starts a tracking server and runs whole sweeps (minutes); only its refusal is checked here.
    completed = run_benchmark("sweep_workers.py", "--workers", "1", "0", timeout=120)
    assert completed.returncode == 2 and completed.stdout == ""
    assert (
        completed.stderr.strip().splitlines()[-1]
        == "sweep_workers.py: error: --workers must each be at least 1, got [1, 0]"
    )


@pytest.mark.slow
def test_policy_speed_prints_every_row_and_training_numbers_that_agree():
    completed = run_benchmark(
        "policy_speed.py",
        "--chunks",
        "2",
        "--batched-calls",
        "1",
        "--train-steps",
        "1",
        "--skip-onnx",
    )
    assert completed.returncode == 0, completed.stderr[-2000:]
    table = {
        match.group(1).strip(): (float(match.group(2)), float(match.group(3)))
        for match in re.finditer(rf"^\| ([^|]+?)\s+\|\s+{NUMBER} \|\s+{NUMBER} \|$", completed.stdout, re.MULTILINE)
    }
    for part in ("total", "prediction", "decoding"):
        median, p90 = table[f"batch 1, 1 thread: {part} per chunk (ms)"]
        assert 0 < median <= p90
    per_call, _ = table["batch 64, 1 thread: total per call (ms)"]
    per_chunk, _ = table["batch 64, 1 thread: total per chunk (ms)"]
    assert per_chunk == pytest.approx(per_call / 64, rel=0.01)
    training = re.findall(rf"{NUMBER} s per step .*?, {NUMBER} samples/s, speed-up x{NUMBER}", completed.stdout)
    assert len(training) >= 1, completed.stdout  # float32, and bfloat16 where `auto` picks it
    for seconds, samples_per_second, speed_up in ((float(value) for value in row) for row in training):
        # Printed rounded (samples/s to a whole number, the speed-up to 0.01), which on a busy host with slow steps is
        # more than 1% off: below 50 samples/s or a speed-up of 0.5.
        assert samples_per_second == pytest.approx(256 / seconds, rel=0.01, abs=0.5)
        assert speed_up == pytest.approx(2.6 / seconds, rel=0.01, abs=0.005)


@pytest.mark.slow
def test_policy_speed_compares_the_attention_kernels_per_batch_size_with_consistent_ratios():
    completed = run_benchmark(
        "policy_speed.py",
        "--compare-attention",
        "--attention-batches",
        "2",
        "4",
        "--train-steps",
        "1",
        "--threads",
        "1",
    )
    assert completed.returncode == 0, completed.stderr[-2000:]
    rows = re.findall(
        rf"^\|\s+(\d+) \|\s+{NUMBER} \|\s+{NUMBER} \|\s+{NUMBER} \| (\w+)\s+\|$", completed.stdout, re.MULTILINE
    )
    assert [int(batch) for batch, *_ in rows] == [2, 4], completed.stdout
    for _, masked, blockwise, ratio, chosen in rows:
        masked, blockwise, ratio = float(masked), float(blockwise), float(ratio)
        # Each figure is printed to 0.001 (half of it either way).
        assert (blockwise - 5e-4) / (masked + 5e-4) - 5e-4 <= ratio <= (blockwise + 5e-4) / (masked - 5e-4) + 5e-4
        assert chosen in {"masked", "blockwise"}


@pytest.mark.slow
def test_policy_families_prints_a_row_per_family_and_variant_with_its_ratio_to_carp_at_both_batch_sizes():
    completed = run_benchmark("policy_families.py", "--tiny", "--rounds", "2", "--batched-rounds", "1")
    assert completed.returncode == 0, completed.stderr[-2000:]
    row = re.compile(
        rf"^\| (\w+)\s+\| ([\w-]+)\s+\| (\w+)\s+\|\s+([\d,]+) \|\s+(\d+) \|\s+{NUMBER} \|\s+{NUMBER} \|"
        rf"\s+{NUMBER} \|\s+(\S+) \|\s+(\S+) \|$",
        flags=re.MULTILINE,
    )
    rows = [match.groups() for match in row.finditer(completed.stdout)]
    assert [(family, inference, backend) for family, inference, backend, *_ in rows] == [
        ("carp", "greedy", "onnxruntime"),
        ("carp", "greedy", "torch"),
        ("diffusion_unet", "DDIM-10", "torch"),
        ("diffusion_unet", "DDPM-10", "torch"),
        ("diffusion_transformer", "DDIM-10", "torch"),
        ("diffusion_transformer", "DDPM-10", "torch"),
        ("next_token", "greedy", "torch"),
        ("vq_bet", "sampled", "torch"),
        ("edm_unet", "Heun-80", "torch"),
        ("consistency_policy", "1-step", "torch"),
        ("consistency_policy", "3-step", "torch"),
    ], completed.stdout
    reference = float(rows[0][5])
    batched_reference = float(rows[1][8])  # CARP in PyTorch: the ONNX Runtime graphs are batch 1 only
    for family, _, backend, _, _, median, _, ratio, per_chunk, batched_ratio in rows:
        assert float(ratio) == pytest.approx(float(median) / reference, rel=0.02, abs=0.06), family
        assert (per_chunk == "-") == (batched_ratio == "-") == (backend == "onnxruntime")
        if backend == "torch":
            assert float(batched_ratio) == pytest.approx(float(per_chunk) / batched_reference, rel=0.02, abs=0.06)
    assert rows[1][9] == "1.0"
    calls = {(family, inference): int(count) for family, inference, _, _, count, *_ in rows}
    assert calls["next_token", "greedy"] == 10 * (1 + 2 + 3 + 4)  # one call per token, L = A * sum(scales)
    assert calls["vq_bet", "sampled"] == 1  # one GPT call per chunk
    assert calls["edm_unet", "Heun-80"] == 2 * 79  # two U-Net calls per Heun step
    assert (calls["consistency_policy", "1-step"], calls["consistency_policy", "3-step"]) == (1, 3)
    single = run_benchmark("policy_families.py", "--tiny", "--rounds", "1", "--skip-batched")
    assert single.returncode == 0 and len(row.findall(single.stdout)) == len(rows)
    assert all(match[8] == match[9] == "-" for match in row.findall(single.stdout))
    failed = run_benchmark("policy_families.py", "--rounds", "0")
    assert failed.returncode == 1 and failed.stderr.startswith("error: --rounds")


@pytest.mark.slow
def test_rendering_cost_prints_both_settings_per_task_and_saves_a_frame_grid(tmp_path):
    completed = run_benchmark(
        "rendering_cost.py", *("--tasks", "lift", "--steps", "3", "--repeats", "2", "--grid-dir", str(tmp_path))
    )
    assert completed.returncode == 0, completed.stderr[-2000:]
    rows = [line for line in completed.stdout.splitlines() if line.startswith("| lift")]
    assert [row.split("|")[2].strip() for row in rows] == ["lean", "robosuite"]
    for row in rows:
        frames, setup, median, p90, per_second = (float(cell) for cell in row.split("|")[3:8])
        assert frames == 6 and setup > 0 and 0 < median <= p90
        assert per_second == pytest.approx(1e3 / median, rel=0.01, abs=0.1)
    assert (tmp_path / "lift_frames.png").stat().st_size > 0


def test_rendering_cost_refuses_an_unknown_task_in_one_line():
    completed = run_benchmark("rendering_cost.py", "--tasks", "peg_in_hole")
    assert completed.returncode == 1
    assert completed.stderr.strip().splitlines() == [
        "error: --tasks ['peg_in_hole']: unknown; expected some of "
        "['can', 'lift', 'nut_assembly', 'square', 'stack', 'stack_three', 'threading']"
    ]


def test_image_windows_prints_bytes_per_demo_and_consistent_window_rates():
    completed = run_benchmark(
        "image_windows.py", *("--demos", "3", "--steps", "12", "--image-size", "16", "--batch-size", "8")
    )
    assert completed.returncode == 0, completed.stderr[-2000:]
    output = completed.stdout
    assert output.startswith("synthetic: 3 demos, 36 frames of 16x16, chunks of 4 frames")
    sizes = {
        match.group(1): (float(match.group(2)), float(match.group(3)), float(match.group(4)))
        for match in re.finditer(rf"^(\w+_image)\s+{NUMBER}\s+{NUMBER}\s+{NUMBER}$", output, flags=re.MULTILINE)
    }
    assert set(sizes) == {"agentview_image", "robot0_eye_in_hand_image"}
    for on_disk, raw, ratio in sizes.values():
        assert raw == 12 * 16 * 16 * 3 and 0 < on_disk < raw
        assert ratio == pytest.approx(raw / on_disk, rel=0.01)
    total = float(re.search(rf"^all cameras\s+{NUMBER}$", output, flags=re.MULTILINE).group(1))
    assert total == pytest.approx(sum(size[0] for size in sizes.values()), abs=1)
    pattern = rf"^(per batch|preloaded)\s+([12])\s+8\s+{NUMBER}\s+{NUMBER}\s+{NUMBER}$"
    rates = re.findall(pattern, output, flags=re.MULTILINE)
    assert [(reads, obs_steps) for reads, obs_steps, *_ in rates] == [
        ("per batch", "1"),
        ("per batch", "2"),
        ("preloaded", "1"),
        ("preloaded", "2"),
    ]
    for _, _, opened, milliseconds, per_second in rates:
        assert float(opened) >= 0
        rounding = 0.0005 / float(milliseconds)  # the printed milliseconds have three decimals
        assert float(per_second) == pytest.approx(8 / (float(milliseconds) / 1e3), rel=0.02 + rounding, abs=1)


def test_image_windows_refuses_a_buffer_without_images_in_one_line(tmp_path):
    completed = run_benchmark("image_windows.py", "--buffer", str(tmp_path))
    assert completed.returncode == 1
    assert completed.stderr.strip().splitlines() == [f"error: --buffer={tmp_path}: not a zarr replay buffer"]


@pytest.mark.slow
def test_serving_latency_prints_in_process_and_loopback_rows_per_backend():
    completed = run_benchmark(
        "serving_latency.py",
        *("--tiny", "--requests", "6", "--clients", "1", "2", "--prediction-threads", "2"),
        *("--agreement-histories", "16"),
    )
    assert completed.returncode == 0, completed.stderr[-2000:]
    torch_header, onnx_header = completed.stdout.splitlines()[:2]
    for header in (torch_header, onnx_header):
        assert "random Lift CARP policy (tiny)" in header and "Do=19, (H, A)=(8, 10)" in header
    assert torch_header.startswith("torch:") and "batching possible" in torch_header  # greedy by default
    assert onnx_header.startswith("onnxruntime:") and "batching never" in onnx_header  # graphs take one request
    pattern = (
        rf"^(torch|onnxruntime)\s+(in-process prediction|loopback round trip)\s+(\d+)\s+(-|on|off)\s+(\d+)"
        rf"\s+{NUMBER}\s+{NUMBER}\s+{NUMBER}\s+{NUMBER}$"
    )
    rows = re.findall(pattern, completed.stdout, flags=re.MULTILINE)
    assert [tuple(row[:5]) for row in rows] == [
        ("torch", "in-process prediction", "1", "-", "1"),
        ("torch", "loopback round trip", "1", "off", "1"),
        ("torch", "loopback round trip", "2", "off", "1"),
        ("torch", "loopback round trip", "1", "on", "1"),
        ("torch", "loopback round trip", "2", "on", "1"),
        ("onnxruntime", "in-process prediction", "1", "-", "1"),
        ("onnxruntime", "loopback round trip", "1", "off", "1"),
        ("onnxruntime", "loopback round trip", "2", "off", "1"),
        ("onnxruntime", "loopback round trip", "1", "off", "2"),
        ("onnxruntime", "loopback round trip", "2", "off", "2"),
    ]
    for *_, batching, _threads, p50, p99, throughput, per_call in rows:
        assert 0 < float(p50) <= float(p99) and float(throughput) > 0
        assert 1.0 <= float(per_call) <= (8.0 if batching == "on" else 1.0)
    assert re.search(r"^onnxruntime against torch, 16 histories: largest difference ", completed.stdout, re.M)
    assert re.search(r"^torch batched \(8 per call\) against alone, 16 histories: \d+ rows", completed.stdout, re.M)


def test_serving_latency_refuses_a_checkpoint_without_its_protocol_in_one_line(tmp_path):
    missing = tmp_path / "policy.pt"
    completed = run_benchmark("serving_latency.py", "--checkpoint", str(missing))
    assert completed.returncode == 1
    assert completed.stderr.strip().splitlines() == [f"error: {missing}: no such model file"]


@pytest.mark.slow
def test_serving_soak_reports_the_servers_memory_at_start_and_end_and_no_failed_session():
    completed = run_benchmark(
        "serving_soak.py", *("--tiny", "--minutes", "0.15", "--clients", "4", "--settle-s", "2", "--report-s", "3")
    )
    assert completed.returncode == 0, completed.stderr[-2000:]
    memory = re.search(
        rf"^server RSS: {NUMBER} MiB when ready, {NUMBER} MiB after 2 s of load \(start\), {NUMBER} MiB at the end",
        completed.stdout,
        flags=re.MULTILINE,
    )
    assert memory and all(float(value) > 0 for value in memory.groups())
    robots = re.search(
        r"^robots: (\d+) sessions .* (\d+) failed sessions; server: 0 connections open", completed.stdout, re.M
    )
    assert robots and int(robots.group(1)) > 4 and int(robots.group(2)) == 0


def test_serving_soak_refuses_a_settling_time_longer_than_the_run_in_one_line():
    completed = run_benchmark("serving_soak.py", "--tiny", "--minutes", "0.5", "--settle-s", "60")
    assert completed.returncode == 1
    assert completed.stderr.strip().splitlines() == ["error: --settle-s must be shorter than the run (--minutes)"]


def test_tokenizer_kinds_prints_a_row_per_setting_with_bits_equal_to_tokens_times_log2_v(synthetic_file, tmp_path):
    from carp.data.ingest import ingest_demonstrations
    from tests.conftest import OBS_KEYS

    ingest_demonstrations(synthetic_file, tmp_path / "data" / "processed" / "lift", OBS_KEYS, valid_fraction=0.25)
    completed = subprocess.run(
        [sys.executable, str(REPO_ROOT / "benchmarks" / "tokenizer_kinds.py"), "--task", "lift"]
        + ["--kinds", "binning", "bspline", "--params", str(REPO_ROOT / "params.yaml")],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert completed.returncode == 0, completed.stderr[-2000:]
    rows = [line.split("|")[1:-1] for line in completed.stdout.splitlines() if line.startswith("| binning |")]
    rows += [line.split("|")[1:-1] for line in completed.stdout.splitlines() if line.startswith("| bspline |")]
    assert [row[1].strip() for row in rows] == [f"bins={n}" for n in (16, 32, 64, 128, 256)] + [
        f"control_points={k}" for k in (4, 6, 8, 12, 16)
    ]
    for row in rows:
        vocabulary, tokens, bits = int(row[2]), float(row[3].split(",")[0]), float(row[4])
        assert bits == pytest.approx(tokens * math.log2(vocabulary), abs=0.5)
    errors = [float(row[6]) for row in rows[:5]]
    assert errors == sorted(errors, reverse=True)  # more bins, less error
