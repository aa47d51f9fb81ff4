"""A bounded soak of `carp serve`: many clients connecting, sending, dropping and reconnecting for minutes.

Serves a policy (`--checkpoint`, else a randomly initialized Lift CARP policy of the default size; `--tiny` for the
test-sized one) with `carp serve` in a child process, on the backend of `--backend`, and runs `--clients` robots
on threads of this process for `--minutes`. Each robot connects, sends a random number of steps (1 to 20, some
observation-only), now and then a malformed request or a hostile frame (200 000 empty maps), then leaves:
half the time with a closing handshake, half the time by dropping its socket; then it connects again. Every
`--report-s` seconds and at the end it prints the server's resident memory (VmRSS of the child process, read from
/proc), its open connections and counters (`/metrics`); the last lines compare the memory at start (after the
first minute's warm-up of allocators and caches, `--settle-s`) and at the end. Linux only (/proc). Not part of CI.

Usage: python benchmarks/serving_soak.py [--checkpoint policy.pt | --tiny] [--minutes 5] [--clients 16]
       [--backend onnxruntime|torch] [--settle-s 60] [--report-s 30]
"""

import argparse
import os
import random
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import msgpack
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for folder in (ROOT, ROOT / "clients" / "python"):
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))

from carp_client import PolicyClient, ServerError  # noqa: E402

from tests.serving.random_policy import LIFT_OBS_WIDTHS, random_lift_policy  # noqa: E402

HOSTILE_FRAME = msgpack.packb([{}] * 200_000)
"""200 000 empty maps in 200 kB: refused by the value limit before msgpack builds any of them."""


def resident_mib(pid: int) -> float:
    """Resident memory of process `pid` in MiB (VmRSS)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for process {pid}")


def metrics(port: int) -> dict[str, float]:
    """The server's unlabelled Prometheus series, by name."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as response:
        text = response.read().decode()
    values = {}
    for line in text.splitlines():
        if line and not line.startswith("#") and "{" not in line:
            name, value = line.split()
            values[name] = float(value)
    return values


def robot(url: str, seed: int, stop: threading.Event, counts: dict[str, int], lock: threading.Lock) -> None:
    """Connect, send, leave and come back until `stop` is set; tally what happened in `counts`."""
    rng = random.Random(seed)
    values = np.random.default_rng(seed)
    while not stop.is_set():
        tally = {"sessions": 1}
        try:
            client = PolicyClient(url, timeout=30, reconnect_budget_s=30)
            client.connect()
            client.reset(seed=rng.randrange(1000))
            for _ in range(rng.randint(1, 20)):
                request = {
                    key: values.uniform(-1, 1, size=width).astype(np.float32) for key, width in LIFT_OBS_WIDTHS.items()
                }
                roll = rng.random()
                try:
                    if roll < 0.05:
                        client.infer({"object": np.zeros(3, np.float32)})  # wrong shape
                    elif roll < 0.08:
                        client._connection.send(HOSTILE_FRAME)
                        reply = client._connection.recv(timeout=30)
                        tally["hostile"] = tally.get("hostile", 0) + isinstance(reply, str)
                    elif roll < 0.4:
                        client.observe(request)
                    else:
                        client.infer(request)
                        tally["chunks"] = tally.get("chunks", 0) + 1
                except ServerError:
                    tally["refused"] = tally.get("refused", 0) + 1
            if rng.random() < 0.5:
                client.close()
            else:
                client._drop()  # the socket goes without a closing handshake, as a robot that loses power
                tally["dropped"] = 1
        except (ConnectionError, TimeoutError, OSError) as error:
            tally["failures"] = 1
            print(f"robot {seed}: {type(error).__name__}: {error}", file=sys.stderr)
        with lock:
            for key, value in tally.items():
                counts[key] = counts.get(key, 0) + value


def wait_ready(port: int, process: subprocess.Popen, timeout_s: float = 300) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"carp serve exited with status {process.returncode}")
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/readyz", timeout=5) as response:
                if response.status == 200:
                    return
        except OSError:
            pass
        time.sleep(0.5)
    raise RuntimeError(f"carp serve was not ready within {timeout_s} s")


def main() -> int:
    """Parse the arguments, serve, soak, print the memory and counters."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--checkpoint", type=Path, help="a policy.pt that records its serving protocol")
    source.add_argument("--tiny", action="store_true", help="the test-sized random policy instead of the default")
    parser.add_argument("--minutes", type=float, default=5.0, help="how long the robots run")
    parser.add_argument("--clients", type=int, default=16, help="robots at once")
    parser.add_argument("--backend", choices=("onnxruntime", "torch"), default="onnxruntime")
    parser.add_argument("--settle-s", type=float, default=60.0, help="seconds of load before the start figure")
    parser.add_argument("--report-s", type=float, default=30.0, help="seconds between two progress lines")
    args = parser.parse_args()
    if args.minutes <= 0 or args.clients < 1 or args.settle_s < 0 or args.report_s <= 0:
        print("error: --minutes, --clients and --report-s must be positive, --settle-s >= 0", file=sys.stderr)
        return 1
    if args.settle_s >= 60 * args.minutes:
        print("error: --settle-s must be shorter than the run (--minutes)", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory() as folder, socket.socket() as probe:
        checkpoint = args.checkpoint
        if checkpoint is None:
            checkpoint = Path(folder) / "policy.pt"
            random_lift_policy(tiny=args.tiny).save(checkpoint)
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
        probe.close()
        command = [sys.executable, "-m", "carp.cli", "serve", "--model", str(checkpoint), "--port", str(port)]
        command += ["--backend", args.backend, "--reload-interval", "0"]
        environment = os.environ | {"PYTHONPATH": str(ROOT / "src")}
        server = subprocess.Popen(command, env=environment, stderr=subprocess.DEVNULL)
        try:
            wait_ready(port, server)
            return soak(server, port, args)
        finally:
            server.terminate()
            server.wait(60)


def soak(server: subprocess.Popen, port: int, args: argparse.Namespace) -> int:
    """Run the robots against the server on `port`; print the progress lines and the memory at start and end."""
    stop, lock, counts = threading.Event(), threading.Lock(), {}
    robots = [
        threading.Thread(target=robot, args=(f"ws://127.0.0.1:{port}", seed, stop, counts, lock), daemon=True)
        for seed in range(args.clients)
    ]
    ready_mib = resident_mib(server.pid)
    started = time.monotonic()
    for thread in robots:
        thread.start()
    print(f"{'elapsed s':>10}{'RSS MiB':>10}{'open':>6}{'requests':>10}{'errors':>8}{'chunks':>8}{'sessions':>10}")
    start_mib = None
    next_report = started + min(args.settle_s, args.report_s) if args.settle_s else started
    end = started + 60 * args.minutes
    while True:
        now = time.monotonic()
        if start_mib is None and now - started >= args.settle_s:
            start_mib = resident_mib(server.pid)
        if now >= next_report or now >= end:
            values = metrics(port)
            with lock:
                chunks, sessions = counts.get("chunks", 0), counts.get("sessions", 0)
            print(
                f"{now - started:>10.0f}{resident_mib(server.pid):>10.1f}{values['carp_serving_connections']:>6.0f}"
                f"{values['carp_serving_requests_total']:>10.0f}{values['carp_serving_errors_total']:>8.0f}"
                f"{chunks:>8}{sessions:>10}"
            )
            next_report = now + args.report_s
        if now >= end:
            break
        time.sleep(min(1.0, max(end - now, 0.01)))
    stop.set()
    for thread in robots:
        thread.join(120)
    time.sleep(2)  # the server notices the last closed connections
    end_mib, values = resident_mib(server.pid), metrics(port)
    print(
        f"server RSS: {ready_mib:.1f} MiB when ready, {start_mib:.1f} MiB after {args.settle_s:.0f} s of load (start), "
        f"{end_mib:.1f} MiB at the end ({end_mib - start_mib:+.1f} MiB over {60 * args.minutes - args.settle_s:.0f} s)"
    )
    print(
        f"robots: {counts.get('sessions', 0)} sessions ({counts.get('dropped', 0)} dropped without closing), "
        f"{counts.get('chunks', 0)} chunks, {counts.get('refused', 0)} malformed requests refused, "
        f"{counts.get('hostile', 0)} hostile frames refused, {counts.get('failures', 0)} failed sessions; "
        f"server: {values['carp_serving_connections']:.0f} connections open after the robots left"
    )
    return 0 if counts.get("failures", 0) == 0 and values["carp_serving_connections"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
