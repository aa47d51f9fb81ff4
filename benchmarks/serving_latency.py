"""Latency of a served CARP policy: in-process prediction against a loopback round trip through `carp serve`.

For the policy of `--checkpoint` (one that records its serving protocol), else a randomly initialized Lift policy of
the default configuration (A = 10, H = 16, depth 8, D = 64; `--tiny` for the test-sized one; speed does not depend
on the weights), measures per chunk, after a warm-up:
- in-process: `predict_action_timed` on a (1, To, Do) observation history, as evaluation calls the policy;
- loopback: `PolicyClient.infer` with one step's per-key observation to a `ServerThread` on 127.0.0.1 in this
  process, from 1 and 4 clients at once (`--clients`), each on its own thread and connection, sending back to back.
  The server predicts one call at a time; each client count runs with batching off (`max_batch_size` 1: a request
  waits for the others' calls) and on (`--max-batch`, 8 by default: requests waiting together share a call, for a
  policy that draws nothing random, e.g. greedy CARP).
Both for each backend of `--backends` (`carp serve --backend`): PyTorch, and CARP's exported graphs in ONNX Runtime,
which take one request per call (no batching rows).

Prints p50 and p99 in milliseconds, the throughput in chunks per second (in-process: one over the mean; loopback:
all clients' timed requests over the wall time of the run) and the mean chunks per prediction call (warm-up
requests included). Predictions run on one torch thread (`--threads`), as
evaluation workers do.

Usage: python benchmarks/serving_latency.py [--checkpoint policy.pt | --tiny] [--requests 200] [--clients 1 4]
       [--max-batch 8] [--backends torch onnxruntime]
"""

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
for folder in (ROOT, ROOT / "clients" / "python"):
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))

from carp_client import PolicyClient  # noqa: E402

from carp.serving.server import PolicyServer, ServerSettings, ServerThread  # noqa: E402
from carp.serving.startup import ServingStartError, load_served_model  # noqa: E402
from tests.serving.random_policy import random_lift_policy  # noqa: E402

WARM_UP_REQUESTS = 5


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


def measure_backend(checkpoint: Path, backend: str, args: argparse.Namespace, label: str) -> list[tuple]:
    """The table rows of `checkpoint` served by `backend`: in-process, then loopback per batching and client count."""
    model, spec = load_served_model(checkpoint, backend=backend)
    print(
        f"{model.backend}: {label}, {model.policy.description}; To={spec.obs_steps}, Do={spec.obs_dim}, "
        f"(H, A)=({spec.action_horizon}, {spec.action_dim}); {args.requests} requests per client after "
        f"{WARM_UP_REQUESTS} warm-up; {args.threads} thread(s); batching "
        f"{'possible' if model.batches else 'never (the policy samples, or its graphs take one request)'}"
    )
    seconds = in_process_seconds(model.policy, spec.obs_steps, spec.obs_dim, args.requests)
    rows = [(model.backend, "in-process prediction", 1, "-", seconds, sum(seconds), 1.0)]
    keys = dict(zip(spec.obs_keys, spec.obs_widths))
    for max_batch in sorted({1, args.max_batch} if model.batches else {1}):
        settings = ServerSettings(port=0, max_batch_size=max_batch)
        with ServerThread(PolicyServer(model, spec, settings)) as server:
            metrics = server.policy_server.metrics
            for clients in args.clients:
                calls, chunks = metrics.model_calls, metrics.predicted_chunks
                seconds, wall = loopback_seconds(server.url, keys, clients, args.requests)
                mean_batch = (metrics.predicted_chunks - chunks) / (metrics.model_calls - calls)
                batching = "off" if max_batch == 1 else "on"
                rows.append((model.backend, "loopback round trip", clients, batching, seconds, wall, mean_batch))
    return rows


def main() -> int:
    """Parse the arguments, measure, print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--checkpoint", type=Path, help="a policy.pt that records its serving protocol")
    source.add_argument("--tiny", action="store_true", help="the test-sized random policy instead of the default")
    parser.add_argument("--requests", type=int, default=200, help="timed requests per client (and in-process)")
    parser.add_argument("--clients", type=int, nargs="+", default=[1, 4], help="concurrent clients of each run")
    parser.add_argument("--threads", type=int, default=1, help="torch threads of the predictions")
    parser.add_argument("--max-batch", type=int, default=8, help="most requests per call with batching on")
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
        except ServingStartError as error:
            print(f"error: {error}", file=sys.stderr)
            return 1
    header = (
        f"{'backend':<13}{'path':<24}{'clients':>8}{'batching':>10}{'p50 ms':>10}{'p99 ms':>10}{'chunks/s':>10}"
        f"{'per call':>10}"
    )
    print(header)
    for backend, name, clients, batching, seconds, wall, mean_batch in rows:
        p50, p99 = percentiles_ms(seconds)
        throughput = len(seconds) / wall
        print(
            f"{backend:<13}{name:<24}{clients:>8}{batching:>10}{p50:>10.2f}{p99:>10.2f}{throughput:>10.1f}"
            f"{mean_batch:>10.2f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
