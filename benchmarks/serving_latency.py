"""Latency of a served CARP policy: in-process prediction against a loopback round trip through `carp serve`.

For the policy of `--checkpoint` (one that records its serving protocol), else a randomly initialized Lift policy of
the default configuration (A = 10, H = 16, depth 8, D = 64; `--tiny` for the test-sized one; speed does not depend
on the weights), measures per chunk, after a warm-up:
- in-process: `predict_action_timed` on a (1, To, Do) observation history, as evaluation calls the PyTorch policy;
- loopback: `PolicyClient.infer` with one step's per-key observation to a `ServerThread` on 127.0.0.1 in this
  process, from 1 and 4 clients at once (`--clients`), each on its own thread and connection. The server serializes
  predictions (one model lock), so with several clients the round trip includes waiting for the others.

Prints p50 and p99 in milliseconds. Predictions run on one torch thread (`--threads`), as evaluation workers do.

Usage: python benchmarks/serving_latency.py [--checkpoint policy.pt | --tiny] [--requests 200] [--clients 1 4]
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


def client_round_trips(url: str, keys: dict[str, int], requests: int, seed: int, out: list[float]) -> None:
    """One client's round-trip seconds of `requests` requests, after a warm-up, appended to `out`."""
    rng = np.random.default_rng(seed)
    with PolicyClient(url, timeout=60) as client:
        client.reset(seed)
        for index in range(WARM_UP_REQUESTS + requests):
            request = {key: rng.uniform(-1, 1, size=width).astype(np.float32) for key, width in keys.items()}
            started = time.perf_counter()
            client.infer(request)
            if index >= WARM_UP_REQUESTS:
                out.append(time.perf_counter() - started)


def loopback_seconds(url: str, keys: dict[str, int], clients: int, requests: int) -> list[float]:
    """Round-trip seconds of every request of `clients` clients sending `requests` requests each at once."""
    results: list[list[float]] = [[] for _ in range(clients)]
    threads = [
        threading.Thread(target=client_round_trips, args=(url, keys, requests, index, results[index]))
        for index in range(clients)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    if any(len(result) != requests for result in results):
        raise RuntimeError("a client did not finish its requests (see the errors above)")
    return [value for result in results for value in result]


def main() -> int:
    """Parse the arguments, measure, print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--checkpoint", type=Path, help="a policy.pt that records its serving protocol")
    source.add_argument("--tiny", action="store_true", help="the test-sized random policy instead of the default")
    parser.add_argument("--requests", type=int, default=200, help="timed requests per client (and in-process)")
    parser.add_argument("--clients", type=int, nargs="+", default=[1, 4], help="concurrent clients of each run")
    parser.add_argument("--threads", type=int, default=1, help="torch threads of the predictions")
    args = parser.parse_args()
    if args.requests < 1 or any(clients < 1 for clients in args.clients) or args.threads < 1:
        print("error: --requests, --clients and --threads must be positive", file=sys.stderr)
        return 1
    torch.set_num_threads(args.threads)

    with tempfile.TemporaryDirectory() as folder:
        checkpoint = args.checkpoint
        if checkpoint is None:
            checkpoint = Path(folder) / "policy.pt"
            random_lift_policy(tiny=args.tiny).save(checkpoint)
        try:
            model, spec = load_served_model(checkpoint)
        except ServingStartError as error:
            print(f"error: {error}", file=sys.stderr)
            return 1
        label = (
            str(args.checkpoint)
            if args.checkpoint
            else f"random Lift CARP policy ({'tiny' if args.tiny else 'default size'})"
        )
        print(
            f"serving latency: {label}, {model.policy.description}; To={spec.obs_steps}, Do={spec.obs_dim}, "
            f"(H, A)=({spec.action_horizon}, {spec.action_dim}); {args.requests} requests per client after "
            f"{WARM_UP_REQUESTS} warm-up; {args.threads} torch thread(s)"
        )
        rows = [
            ("in-process prediction", 1, in_process_seconds(model.policy, spec.obs_steps, spec.obs_dim, args.requests))
        ]
        keys = dict(zip(spec.obs_keys, spec.obs_widths))
        with ServerThread(PolicyServer(model, spec, ServerSettings(port=0))) as server:
            for clients in args.clients:
                rows.append(
                    ("loopback round trip", clients, loopback_seconds(server.url, keys, clients, args.requests))
                )
    print(f"{'path':<24}{'clients':>8}{'p50 ms':>10}{'p99 ms':>10}")
    for name, clients, seconds in rows:
        p50, p99 = percentiles_ms(seconds)
        print(f"{name:<24}{clients:>8}{p50:>10.2f}{p99:>10.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
