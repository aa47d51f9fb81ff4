"""The default pipeline's training and evaluation with a CUDA device, in a few minutes: step time and latency.

Usage: benchmarks/gpu_check.sh [--workspace DIR] [--policies carp,next_token] [--epochs 5] [--num-processes 1]

CUDA has to be visible to torch; without it the check stops at once with one `error:` line and creates nothing. It
copies the project's source files into a fresh workspace (DIR, or a new temporary directory, kept and named at the
end), sets `device: cuda` and short settings (the lift task, 10 demos, 5 tokenizer and policy epochs, 8 evaluation
episodes; models at their default sizes), runs `dvc repro evaluate@lift-<policy>-0` for each policy and prints:

- training on CUDA: precision, milliseconds per optimizer step (median over the epochs after the first, which pays
  for CUDA's start-up) and windows per second;
- evaluation (simulator workers on the CPU, as the pipeline runs them): success rate and latency per chunk;
- the trained policy on CUDA: latency per chunk (prediction plus decoding) at batch 1 and at batch 64, medians of
  timed calls after warm-up calls.

`--num-processes N` trains on N GPUs at once (`training.num_processes`).
"""

import argparse
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

PROJECT_DIR = Path(__file__).resolve().parents[1]
TASK = "lift"
BATCH_1_CALLS = 50
WARMUP_CALLS = 3


def fail(message: str) -> None:
    """Print a one-line error and exit with status 1."""
    print(f"error: gpu_check: {message}", file=sys.stderr)
    sys.exit(1)


def cuda_description() -> str:
    """`<GPU name>, torch <version>, CUDA <version>`; exits with one line when torch sees no CUDA device."""
    import torch

    if not torch.cuda.is_available():
        built = f"built for CUDA {torch.version.cuda}" if torch.version.cuda else "built without CUDA"
        fail(f"no CUDA device is visible to torch {torch.__version__} ({built}); run this on a machine with a GPU")
    return f"{torch.cuda.get_device_name(0)}, torch {torch.__version__}, CUDA {torch.version.cuda}"


def check_params(policies: list[str], epochs: int, num_processes: int) -> dict:
    """Overrides of params.yaml for the check: CUDA, the lift task, short collection, training and evaluation."""
    return {
        "device": "cuda",
        "tasks": [TASK],
        "policies": policies,
        "data": {"num_demos": 10, "num_demos_per_task": {}},
        "tokenizer": {"epochs": epochs, "tasks": []},
        "training": {"epochs": epochs, "epochs_per_task": {}, "num_processes": num_processes},
        "eval": {"episodes": 8, "workers": 8, "video": False},
    }


def merged(base: dict, override: dict) -> dict:
    """`base` with `override`'s keys replaced, recursing into mappings present in both."""
    result = dict(base)
    for key, value in override.items():
        result[key] = merged(base[key], value) if isinstance(value, dict) and isinstance(base.get(key), dict) else value
    return result


def make_workspace(directory: Path, overrides: dict) -> None:
    """Copy the project's source files (not data, models, reports) into `directory`, a new git repository."""
    listed = subprocess.run(
        ["git", "ls-files", "-co", "--exclude-standard"], cwd=PROJECT_DIR, capture_output=True, text=True, check=True
    )
    for name in listed.stdout.splitlines():
        source = PROJECT_DIR / name
        if source.is_file() and not name.startswith(("data/", "models/", "reports/", "checkpoints/")):
            (directory / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, directory / name)
    params = merged(yaml.safe_load((directory / "params.yaml").read_text()), overrides)
    (directory / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    for command in (
        ["git", "init", "-q"],
        ["git", "add", "-A"],
        ["git", "-c", "user.name=gpu-check", "-c", "user.email=gpu-check@localhost", "commit", "-qm", "gpu check"],
    ):
        subprocess.run(command, cwd=directory, check=True)


def training_summary(history_csv: Path, batch_size: int) -> dict[str, float]:
    """Milliseconds per optimizer step and windows per second from a `train_policy` history.

    The first epoch is left out when there are others: it pays for CUDA's start-up (kernel loading, autotuning).
    """
    history = pd.read_csv(history_csv)
    epochs = history.iloc[1:] if len(history) > 1 else history
    windows = round(float(epochs["samples_per_second"].iloc[0] * epochs["epoch_seconds"].iloc[0]))
    steps = math.ceil(windows / batch_size)
    return {
        "step_ms": 1000.0 * statistics.median(epochs["epoch_seconds"]) / steps,
        "windows_per_second": statistics.median(epochs["samples_per_second"]),
        "steps_per_epoch": steps,
        "epochs": len(history),
    }


def cuda_latency(workspace: Path, policy_name: str) -> dict[str, float]:
    """Median milliseconds per chunk of the trained policy on CUDA at batch 1 and 64 (prediction plus decoding)."""
    import torch

    from carp.config import load_params
    from carp.data.dataset import load_task_windows
    from carp.policies.registry import load_policy

    params = load_params(workspace / "params.yaml")
    policy = load_policy(workspace / "models/policy" / TASK / policy_name / "seed0" / "policy.pt", map_location="cuda")
    policy.configure_inference(**params.inference_settings(policy_name, TASK))
    data = params.data
    windows = load_task_windows(workspace / "data/processed" / TASK, data.action_horizon, data.obs_steps,
                                data.action_steps)  # fmt: skip
    observations = windows.valid_obs if len(windows.valid_obs) else windows.train_obs
    generator = torch.Generator(device="cuda").manual_seed(0)
    latency = {}
    for batch_size, calls in ((1, BATCH_1_CALLS), (64, BATCH_1_CALLS // 5)):
        batch = torch.as_tensor(observations[np.arange(batch_size) % len(observations)], dtype=torch.float32)
        seconds = []
        for call in range(WARMUP_CALLS + calls):
            timed = policy.predict_action_timed(batch, generator=generator)
            torch.cuda.synchronize()
            if call >= WARMUP_CALLS:
                seconds.append(timed.prediction_seconds + timed.decoding_seconds)
        latency[f"batch_{batch_size}_ms"] = 1000.0 * statistics.median(seconds)
    return latency


def report(workspace: Path, policy_name: str, batch_size: int) -> str:
    """The check's lines for one policy."""
    training = training_summary(workspace / "reports/policy" / TASK / policy_name / "seed0" / "history.csv", batch_size)
    evaluation = json.loads((workspace / "reports/eval" / TASK / policy_name / "seed0.json").read_text())
    latency = cuda_latency(workspace, policy_name)
    cpu_chunk = evaluation["latency_predict_ms_median"] + evaluation["latency_decode_ms_median"]
    return "\n".join(
        [
            f"{policy_name}:",
            f"  training on CUDA: {training['step_ms']:.2f} ms per step of {batch_size} windows "
            f"({training['windows_per_second']:.0f} windows/s, {training['steps_per_epoch']} steps per epoch, "
            f"{training['epochs']} epochs)",
            f"  evaluation ({evaluation['backend']} on the CPU workers): success {evaluation['successes']}/"
            f"{evaluation['episodes']}, {cpu_chunk:.2f} ms per chunk at batch 1",
            f"  on CUDA: {latency['batch_1_ms']:.2f} ms per chunk at batch 1, {latency['batch_64_ms']:.2f} ms per "
            "batch of 64 chunks",
        ]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--workspace", type=Path, help="an empty or missing directory; default: a new temporary one")
    parser.add_argument("--policies", default="carp", help="comma-separated policy families (default: carp)")
    parser.add_argument("--epochs", type=int, default=5, help="tokenizer and policy epochs (default: 5)")
    parser.add_argument("--num-processes", type=int, default=1, help="training processes, one GPU each (default: 1)")
    args = parser.parse_args()
    if args.epochs < 1:
        fail(f"--epochs {args.epochs}: must be >= 1")
    if args.workspace is not None and args.workspace.exists() and any(args.workspace.iterdir()):
        fail(f"--workspace {args.workspace}: not empty")
    description = cuda_description()
    import torch

    if args.num_processes > torch.cuda.device_count():
        fail(f"--num-processes {args.num_processes}: {torch.cuda.device_count()} CUDA devices visible")
    policies = [name for name in args.policies.split(",") if name]
    workspace = args.workspace or Path(tempfile.mkdtemp(prefix="carp-gpu-check-"))
    workspace.mkdir(parents=True, exist_ok=True)
    make_workspace(workspace, check_params(policies, args.epochs, args.num_processes))
    print(f"{description}; workspace {workspace}", flush=True)
    # Stage commands call `python` and `dvc`: this interpreter's environment comes first on PATH.
    environment = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    for policy_name in policies:
        stage = f"evaluate@{TASK}-{policy_name}-0"
        with (workspace / f"gpu_check_{policy_name}.log").open("w") as log:
            completed = subprocess.run(
                [sys.executable, "-m", "dvc", "repro", stage],
                cwd=workspace,
                env=environment,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        if completed.returncode != 0:
            tail = (workspace / f"gpu_check_{policy_name}.log").read_text().splitlines()[-20:]
            print("\n".join(tail), file=sys.stderr)
            fail(f"dvc repro {stage} failed; its log is {workspace / f'gpu_check_{policy_name}.log'}")
        batch_size = yaml.safe_load((workspace / "params.yaml").read_text())["training"]["batch_size"]
        print(report(workspace, policy_name, batch_size), flush=True)


if __name__ == "__main__":
    main()
