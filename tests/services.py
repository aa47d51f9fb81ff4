"""Real services for tests, started and stopped with the project's own scripts in ``tools/`` as a user would.

Each lives in its own temporary directory on free loopback ports and is stopped (and its directory removed) when
its context ends, also when the test fails. The directories are made under ``/tmp`` and left open to others, because
under root PostgreSQL runs as an unprivileged account that must enter them (pytest's own temporary directories are
private to root).
"""

import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TOOLS = REPO / "tools"
# A cold `mlflow server` imports a lot and migrates a new database; two cores shared with other tests are slow.
START_SECONDS = 600


def tool(script: str, *arguments: str, env: dict | None = None, timeout: float = START_SECONDS):
    """Run ``tools/<script>`` with this interpreter; returns the completed process (never raises on failure)."""
    return subprocess.run(
        [sys.executable, str(TOOLS / script), *arguments],
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, **(env or {})},
    )


@contextmanager
def service_directory(prefix: str) -> Iterator[Path]:
    """A fresh directory under the system's temporary directory that other accounts may enter; removed afterwards."""
    directory = Path(tempfile.mkdtemp(prefix=prefix))
    directory.chmod(0o755)
    try:
        yield directory
    finally:
        shutil.rmtree(directory, ignore_errors=True)


@contextmanager
def tracking_server(directory: Path, *options: str, env: dict | None = None) -> Iterator[str]:
    """``tools/tracking_server.py start`` in ``directory`` on a free port; yields the server's URL, stops it after."""
    started = tool("tracking_server.py", "start", "--dir", str(directory), "--port", "0", *options, env=env)
    try:
        assert started.returncode == 0, started.stdout + started.stderr
        status = tool("tracking_server.py", "status", "--dir", str(directory), timeout=60)
        assert status.returncode == 0, status.stdout + status.stderr
        yield status.stdout.strip()
    finally:
        tool("tracking_server.py", "stop", "--dir", str(directory), timeout=120)


@contextmanager
def object_store(directory: Path) -> Iterator[dict[str, str]]:
    """``tools/object_store.py start`` in ``directory`` on a free port; yields its S3 client variables."""
    started = tool("object_store.py", "start", "--dir", str(directory), "--port", "0")
    try:
        assert started.returncode == 0, started.stdout + started.stderr
        printed = tool("object_store.py", "env", "--dir", str(directory), timeout=60)
        assert printed.returncode == 0, printed.stderr
        variables = dict(line.removeprefix("export ").split("=", 1) for line in printed.stdout.splitlines())
        yield variables
    finally:
        tool("object_store.py", "stop", "--dir", str(directory), timeout=120)


def s3_keys(variables: dict[str, str], bucket: str, prefix: str = "") -> list[str]:
    """Every object key under ``prefix`` in ``bucket`` of the store the variables point at."""
    import boto3

    client = boto3.client(
        "s3",
        endpoint_url=variables["AWS_ENDPOINT_URL_S3"],
        aws_access_key_id=variables["AWS_ACCESS_KEY_ID"],
        aws_secret_access_key=variables["AWS_SECRET_ACCESS_KEY"],
        region_name=variables["AWS_DEFAULT_REGION"],
    )
    keys = []
    for page in client.get_paginator("list_objects_v2").paginate(Bucket=bucket, Prefix=prefix):
        keys += [entry["Key"] for entry in page.get("Contents", [])]
    return keys
