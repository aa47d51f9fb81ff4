"""Latency of a served CARP policy: in-process prediction against a loopback round trip through `carp serve`.

For the policy of `--checkpoint` (one that records its serving protocol), else a randomly initialized Lift policy of
the default configuration (A = 10, H = 16, depth 8, D = 64; `--tiny` for the test-sized one; speed does not depend
on the weights), measures per chunk, after a warm-up:
- in-process: `predict_action_timed` on a (1, To, Do) observation history, as evaluation calls the policy;
- loopback: `PolicyClient.infer` with one step's per-key observation to `carp serve` in a child process on
  127.0.0.1 (so that the clients' Python does not share the server's interpreter lock, as robots' would not), from
  1, 4 and 8 clients at once (`--clients`), each on its own thread and connection, sending back to back.
  PyTorch predicts one call at a time; each client count runs with batching off (`--max-batch 1`, the server's
  default: a request waits for the others' calls) and on (`--max-batch`, 8 by default: requests waiting together
  share a call, for a policy that draws nothing random, e.g. greedy CARP; `--batch-window-ms` lets a lone request
  wait for company). CARP's exported graphs in ONNX Runtime take one request per call and run calls
  concurrently: each client count runs on one prediction thread and on `--prediction-threads` (default: one per
  CPU core, the server's default).
Both for each backend of `--backends` (`carp serve --backend`) in the same run.

Prints p50 and p99 in milliseconds, the throughput in chunks per second (in-process: one over the mean; loopback:
all clients' timed requests over the wall time of the run) and the mean chunks per prediction call (warm-up
requests included). Predictions run on one torch thread (`--threads`), as evaluation workers do. Then two
agreement lines over `--agreement-histories` random histories: the ONNX graphs' chunks against PyTorch's (largest
difference, chunks further apart than 1e-3), and, for a greedy PyTorch policy, batched rows (8 per call) against
each history predicted alone (a row further than 1e-3 away chose another token somewhere: a flip on a near tie).

Usage: python benchmarks/serving_latency.py [--checkpoint policy.pt | --tiny] [--requests 200] [--clients 1 4 8]
       [--max-batch 8] [--batch-window-ms 0] [--prediction-threads 0] [--backends torch onnxruntime]
       [--agreement-histories 512]
"""

import argparse
import contextlib
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
for folder in (ROOT, ROOT / "clients" / "python"):
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))

from carp_client import PolicyClient  # noqa: E402

from carp.serving.startup import ServingStartError, load_served_model  # noqa: E402
from tests.serving.random_policy import random_lift_policy  # noqa: E402

WARM_UP_REQUESTS = 5
FLIP_TOLERANCE = 1e-3
"""A chunk further than this from another chose another token somewhere (float rounding alone moves it ~1e-6)."""


def percentiles_ms(seconds: list[float]) -> tuple[float, float]:
    """(p50, p99) of `seconds`, in milliseconds."""
    return tuple(float(value) * 1e3 for value in np.percentile(seconds, [50, 99]))


def in_process_seconds(policy, obs_steps: int, obs_dim: int, requests: int) -> list[float]:
    """Seconds of each of `requests` predictions on random (1, To, Do) histories, after a warm-up."""
    rng = np.random.default_rng(0)
    generator = torch.Generator().manual_seed(0)
    histories = rng.uniform(-1, 1, size=(WARM_UP_REQUESTS + requests, 1, obs_steps, obs_dim)).astype(np.float32)
    seconds = []
    for index, history in enumerate(histories):
        started = time.perf_counter()
        policy.predict_action_timed(history, generator=generator)
        if index >= WARM_UP_REQUESTS:
            seconds.append(time.perf_counter() - started)
    return seconds


def client_round_trips(
    url: str, keys: dict[str, int], requests: int, seed: int, out: list[float], span: list[float]
) -> None:
    """One client's round-trip seconds of `requests` requests, after a warm-up, appended to `out`; `span` receives
    the `perf_counter` times its first timed request left and its last reply arrived."""
    rng = np.random.default_rng(seed)
    with PolicyClient(url, timeout=60) as client:
        client.reset(seed)
        for index in range(WARM_UP_REQUESTS + requests):
            request = {key: rng.uniform(-1, 1, size=width).astype(np.float32) for key, width in keys.items()}
            started = time.perf_counter()
            client.infer(request)
            finished = time.perf_counter()
            if index == WARM_UP_REQUESTS:
                span.append(started)
            if index >= WARM_UP_REQUESTS:
                out.append(finished - started)
        span.append(finished)


def loopback_seconds(url: str, keys: dict[str, int], clients: int, requests: int) -> tuple[list[float], float]:
    """Round-trip seconds of every request of `clients` clients sending `requests` requests each at once.

    Returns:
        The seconds, and the wall seconds from the first timed request sent to the last reply received.
    """
    results: list[list[float]] = [[] for _ in range(clients)]
    spans: list[list[float]] = [[] for _ in range(clients)]
    threads = [
        threading.Thread(target=client_round_trips, args=(url, keys, requests, index, results[index], spans[index]))
        for index in range(clients)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    if any(len(result) != requests for result in results):
        raise RuntimeError("a client did not finish its requests (see the errors above)")
    wall = max(span[1] for span in spans) - min(span[0] for span in spans)
    return [value for result in results for value in result], wall


@contextlib.contextmanager
def served(checkpoint: Path, backend: str, max_batch: int, threads: int, window_ms: float, torch_threads: int):
    """`carp serve` of `checkpoint` in a child process on a free loopback port; yields the port once it is ready."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    command = [sys.executable, "-m", "carp.cli", "serve", "--model", str(checkpoint), "--port", str(port)]
    command += ["--backend", backend, "--max-batch", str(max_batch), "--prediction-threads", str(threads)]
    command += ["--batch-window-ms", str(window_ms), "--reload-interval", "0"]
    environment = os.environ | {"PYTHONPATH": str(ROOT / "src"), "OMP_NUM_THREADS": str(torch_threads)}
    server = subprocess.Popen(command, env=environment, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while True:
            if server.poll() is not None:
                raise RuntimeError(f"carp serve exited: {server.stderr.read().strip()[-500:]}")
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/readyz", timeout=5) as response:
                    if response.status == 200:
                        break
            except OSError:
                if time.monotonic() > deadline:
                    raise RuntimeError("carp serve was not ready within 300 s") from None
                time.sleep(0.2)
        yield port
    finally:
        server.terminate()
        server.communicate(timeout=60)


def calls_and_chunks(port: int) -> tuple[float, float]:
    """The server's prediction calls and predicted chunks so far (`/metrics`)."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as response:
        values = dict(
            line.split() for line in response.read().decode().splitlines() if line and not line.startswith("#")
        )
    return float(values["carp_serving_model_calls_total"]), float(values["carp_serving_predicted_chunks_total"])


def measure_backend(checkpoint: Path, backend: str, args: argparse.Namespace, label: str) -> list[tuple]:
    """The table rows of `checkpoint` served by `backend`: in-process, then loopback per setting and client count."""
    model, spec = load_served_model(checkpoint, backend=backend)
    threads = args.prediction_threads or os.cpu_count() or 1
    if model.batches:
        mode = "batching possible"
        settings = [(1, 1, "off"), (args.max_batch, 1, "on")] if args.max_batch > 1 else [(1, 1, "off")]
    elif model.concurrent:
        mode = f"batching never (graphs take one request), calls on 1 and {threads} threads"
        settings = sorted({(1, 1, "off"), (1, threads, "off")}, key=lambda setting: setting[1])
    else:
        mode = "batching never (the policy samples)"
        settings = [(1, 1, "off")]
    print(
        f"{model.backend}: {label}, {model.policy.description}; To={spec.obs_steps}, Do={spec.obs_dim}, "
        f"(H, A)=({spec.action_horizon}, {spec.action_dim}); {args.requests} requests per client after "
        f"{WARM_UP_REQUESTS} warm-up; {args.threads} torch thread(s); {mode}"
    )
    seconds = in_process_seconds(model.policy, spec.obs_steps, spec.obs_dim, args.requests)
    rows = [(model.backend, "in-process prediction", 1, "-", 1, seconds, sum(seconds), 1.0)]
    keys = dict(zip(spec.obs_keys, spec.obs_widths))
    for max_batch, prediction_threads, batching in settings:
        window_ms = args.batch_window_ms if batching == "on" else 0.0
        with served(checkpoint, backend, max_batch, prediction_threads, window_ms, args.threads) as port:
            for clients in args.clients:
                calls, chunks = calls_and_chunks(port)
                seconds, wall = loopback_seconds(f"ws://127.0.0.1:{port}", keys, clients, args.requests)
                calls_after, chunks_after = calls_and_chunks(port)
                mean_batch = (chunks_after - chunks) / (calls_after - calls)
                rows.append(
                    (model.backend, "loopback round trip", clients, batching, prediction_threads, seconds, wall,
                     mean_batch)
                )  # fmt: skip
    return rows


def agreement_lines(checkpoint: Path, histories: int) -> list[str]:
    """How far the ONNX graphs' chunks are from PyTorch's, and batched greedy rows from their chunks alone."""
    from carp.serving.session import Observed

    in_torch, spec = load_served_model(checkpoint, backend="torch")
    in_onnx, _ = load_served_model(checkpoint, backend="onnxruntime")
    rng = np.random.default_rng(1)
    observed = [
        Observed(rng.uniform(-1, 1, size=(spec.obs_steps, spec.obs_dim)).astype(np.float32), None, torch.Generator())
        for _ in range(histories)
    ]
    alone = np.stack([in_torch.predict(item)[0].actions[0] for item in observed])  # (N, H, A)
    lines = []
    if in_onnx.backend == "onnxruntime":
        graphs = np.stack([in_onnx.predict(item)[0].actions[0] for item in observed])
        differences = np.abs(graphs - alone).reshape(histories, -1).max(axis=1)
        lines.append(
            f"onnxruntime against torch, {histories} histories: largest difference {differences.max():.2e}, "
            f"chunks further apart than {FLIP_TOLERANCE:g}: {int((differences > FLIP_TOLERANCE).sum())}"
        )
    if in_torch.batches:
        batched = np.concatenate(
            [in_torch.predict_batch(observed[start : start + 8])[0].actions for start in range(0, histories, 8)]
        )
        differences = np.abs(batched - alone).reshape(histories, -1).max(axis=1)
        flips = int((differences > FLIP_TOLERANCE).sum())
        rounding = differences[differences <= FLIP_TOLERANCE]
        lines.append(
            f"torch batched (8 per call) against alone, {histories} histories: {flips} rows flipped a token "
            f"({100 * flips / histories:.1f}%), largest difference {differences.max():.2e}, the others within "
            f"{(rounding.max() if rounding.size else 0.0):.2e}"
        )
    return lines


def main() -> int:
    """Parse the arguments, measure, print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--checkpoint", type=Path, help="a policy.pt that records its serving protocol")
    source.add_argument("--tiny", action="store_true", help="the test-sized random policy instead of the default")
    parser.add_argument("--requests", type=int, default=200, help="timed requests per client (and in-process)")
    parser.add_argument("--clients", type=int, nargs="+", default=[1, 4, 8], help="concurrent clients of each run")
    parser.add_argument("--threads", type=int, default=1, help="torch threads of the predictions")
    parser.add_argument("--max-batch", type=int, default=8, help="most requests per call with batching on")
    parser.add_argument("--batch-window-ms", type=float, default=0.0, help="batching window with batching on")
    parser.add_argument(
        "--prediction-threads", type=int, default=0, help="ONNX Runtime calls at once (0: one per CPU core)"
    )
    parser.add_argument(
        "--agreement-histories", type=int, default=512, help="histories of the agreement lines (0: none)"
    )
    parser.add_argument(
        "--backends",
        nargs="+",
        choices=("torch", "onnxruntime"),
        default=["torch", "onnxruntime"],
        help="what predicts",
    )
    args = parser.parse_args()
    if min(args.requests, *args.clients, args.threads, args.max_batch) < 1:
        print("error: --requests, --clients, --threads and --max-batch must be positive", file=sys.stderr)
        return 1
    if min(args.prediction_threads, args.agreement_histories, args.batch_window_ms) < 0:
        print("error: --prediction-threads, --agreement-histories and --batch-window-ms must be >= 0", file=sys.stderr)
        return 1
    torch.set_num_threads(args.threads)

    with tempfile.TemporaryDirectory() as folder:
        checkpoint = args.checkpoint
        if checkpoint is None:
            checkpoint = Path(folder) / "policy.pt"
            random_lift_policy(tiny=args.tiny).save(checkpoint)
        label = (
            str(args.checkpoint)
            if args.checkpoint
            else f"random Lift CARP policy ({'tiny' if args.tiny else 'default size'})"
        )
        try:
            rows = [row for backend in args.backends for row in measure_backend(checkpoint, backend, args, label)]
            agreement = agreement_lines(checkpoint, args.agreement_histories) if args.agreement_histories else []
        except ServingStartError as error:
            print(f"error: {error}", file=sys.stderr)
            return 1
    header = (
        f"{'backend':<13}{'path':<24}{'clients':>8}{'batching':>10}{'threads':>8}{'p50 ms':>10}{'p99 ms':>10}"
        f"{'chunks/s':>10}{'per call':>10}"
    )
    print(header)
    for backend, name, clients, batching, threads, seconds, wall, mean_batch in rows:
        p50, p99 = percentiles_ms(seconds)
        throughput = len(seconds) / wall
        print(
            f"{backend:<13}{name:<24}{clients:>8}{batching:>10}{threads:>8}{p50:>10.2f}{p99:>10.2f}"
            f"{throughput:>10.1f}{mean_batch:>10.2f}"
        )
    for line in agreement:
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
