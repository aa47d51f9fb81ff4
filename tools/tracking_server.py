"""Start or stop a shared MLflow tracking server backed by PostgreSQL, all kept in one directory.

    python tools/tracking_server.py start --dir DIR [--port 5000] [--host 127.0.0.1] [--db-port N]
        [--artifacts-destination URI] [--workers 2] [--allowed-hosts HOSTS] [--pg-bin DIR] [--db-user NAME]
    python tools/tracking_server.py stop --dir DIR
    python tools/tracking_server.py status --dir DIR
    python tools/tracking_server.py sweep-storage --dir DIR

``start`` creates a PostgreSQL cluster in ``DIR/postgres`` with the server binaries of Debian's ``postgresql``
package (``initdb``, ``pg_ctl``), starts it on loopback only, creates the ``mlflow`` database, and starts
``mlflow server`` on it with ``--artifacts-destination`` (``DIR/artifacts`` unless given; an ``s3://`` URI takes
the usual ``AWS_*`` and ``MLFLOW_S3_ENDPOINT_URL`` variables from the environment), so clients upload and download
artifacts through the server and need no access to the storage. Each step is skipped when already done, so a second
``start`` (after a reboot, say) brings back whatever is down. Point carp at the server with the param
``tracking.uri: http://HOST:PORT``.

The same cluster holds an ``optuna`` database for sweep workers sharing one Optuna study: ``sweep-storage`` prints its
URL for the param ``sweep.storage`` (the password stays out of it; libpq reads it from ``PGPASSFILE`` or
``~/.pgpass``).

PostgreSQL refuses to run as root, so under root the cluster belongs to ``--db-user`` (the ``postgres`` account the
Debian package creates, else ``nobody``), which must be able to reach ``DIR``. The database listens on 127.0.0.1 only
and takes a password, kept in ``DIR/pgpass`` (mode 600) for the MLflow server.
"""

import argparse
import glob
import os
import pwd
import re
import secrets
import shutil
import subprocess
import sys
from pathlib import Path

from service_support import (
    LOOPBACK,
    answers,
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

DATABASE = "mlflow"
# The sweep's Optuna study lives beside the runs, so that one command gives a lab both shared stores.
SWEEP_DATABASE = "optuna"
DATABASE_ROLE = "mlflow"
# A cold `mlflow server` imports a lot and migrates a new database's schema; two cores shared with training is slow.
STATE_FILE = "tracking.json"
STARTUP_SECONDS = 240
POSTGRES_STARTUP_SECONDS = 60
PREFERRED_POSTGRES_MAJOR = 15


def find_postgres_binaries(explicit: str | None) -> Path:
    """The directory holding ``initdb`` and ``pg_ctl``.

    Looked for in ``--pg-bin``, else Debian's ``/usr/lib/postgresql/<major>/bin`` (15 first, else the newest), else
    on ``PATH``.
    """
    needed = ("initdb", "pg_ctl")
    if explicit:
        candidates = [Path(explicit)]
    else:

        def major(path: str) -> int:
            found = re.search(r"/postgresql/(\d+)/bin$", path)
            return int(found.group(1)) if found else -1

        debian = sorted(
            glob.glob("/usr/lib/postgresql/*/bin"), key=lambda p: (major(p) != PREFERRED_POSTGRES_MAJOR, -major(p))
        )
        on_path = [Path(found).parent for found in [shutil.which("initdb")] if found]
        candidates = [Path(p) for p in debian] + on_path
    for directory in candidates:
        if all(os.access(directory / name, os.X_OK) for name in needed):
            return directory
    searched = explicit or "/usr/lib/postgresql/*/bin and PATH"
    fail(
        f"PostgreSQL server programs initdb and pg_ctl not found in {searched}: install Debian's postgresql package "
        "(apt-get install postgresql) or name their directory with --pg-bin"
    )


def database_account(requested: str | None) -> pwd.struct_passwd | None:
    """The account that owns and runs the cluster, or ``None`` to run it as the current user (not root)."""
    if os.geteuid() != 0:
        if requested and requested != pwd.getpwuid(os.geteuid()).pw_name:
            fail(f"--db-user={requested}: only root can run the database as another user")
        return None
    names = [requested] if requested else ["postgres", "nobody"]
    for name in names:
        try:
            account = pwd.getpwnam(name)
        except KeyError:
            continue
        if account.pw_uid != 0:
            return account
    fail(f"--db-user={requested}: PostgreSQL refuses to run as root and there is no such unprivileged user")


def as_account(command: list[str], account: pwd.struct_passwd | None) -> list[str]:
    """``command`` run as ``account`` (via runuser, which root needs no password for)."""
    return command if account is None else ["runuser", "-u", account.pw_name, "--", *command]


def run_checked(command: list[str], what: str, cwd: Path, env: dict | None = None) -> str:
    """Run a short command; fail with its output when it exits non-zero."""
    completed = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True)
    if completed.returncode != 0:
        fail(f"{what} failed (exit status {completed.returncode}):\n{(completed.stdout + completed.stderr)[-3000:]}")
    return completed.stdout


def check_reachable(directory: Path, account: pwd.struct_passwd | None) -> None:
    """Fail when the database account cannot enter ``directory`` (a private parent such as ``/root``).

    A directory not created yet is judged by its nearest existing parent (it is created open to others).
    """
    if account is None:
        return
    existing = next(path for path in (directory, *directory.parents) if path.exists())
    probe = subprocess.run(as_account(["test", "-x", str(existing)], account), cwd="/", capture_output=True)
    if probe.returncode != 0:
        fail(
            f"DIR={directory}: user {account.pw_name}, who runs the database (PostgreSQL refuses root), cannot reach "
            "this directory; choose one whose parents others may enter (chmod o+x), e.g. under /srv or /tmp"
        )


def initialize_cluster(binaries: Path, data: Path, account, password_file: Path, directory: Path) -> None:
    """``initdb`` a cluster in ``data`` whose superuser ``mlflow`` logs in with the password in ``password_file``."""
    data.mkdir(mode=0o700)
    one_time = directory / ".initdb-password"
    one_time.write_text(password_file.read_text().rsplit(":", 1)[1])
    if account is not None:
        os.chown(data, account.pw_uid, account.pw_gid)
        os.chown(one_time, account.pw_uid, account.pw_gid)
    try:
        run_checked(
            as_account(
                [
                    str(binaries / "initdb"),
                    "--pgdata", str(data),
                    "--username", DATABASE_ROLE,
                    "--pwfile", str(one_time),
                    "--auth", "scram-sha-256",
                    "--encoding", "UTF8",
                    "--no-locale",
                ],
                account,
            ),
            "initdb",
            cwd=directory,
        )  # fmt: skip
    except SystemExit:
        shutil.rmtree(data, ignore_errors=True)
        raise
    finally:
        one_time.unlink(missing_ok=True)


def postgres_running(binaries: Path, data: Path, account, directory: Path) -> bool:
    """Whether the cluster's postmaster is up (``pg_ctl status``)."""
    status = subprocess.run(
        as_account([str(binaries / "pg_ctl"), "status", "--pgdata", str(data)], account),
        cwd=directory,
        capture_output=True,
        text=True,
    )
    return status.returncode == 0


def start_postgres(binaries: Path, data: Path, account, port: int, directory: Path) -> None:
    """Start the cluster on 127.0.0.1:``port`` (TCP only: no Unix socket) and wait until it accepts connections."""
    options = f"-c listen_addresses={LOOPBACK} -c port={port} -c unix_socket_directories=''"
    run_checked(
        as_account(
            [
                str(binaries / "pg_ctl"), "start",
                "--pgdata", str(data),
                "--log", str(data / "postgresql.log"),
                "--options", options,
                "--wait", "--timeout", str(POSTGRES_STARTUP_SECONDS),
            ],
            account,
        ),
        f"starting PostgreSQL (log: {data / 'postgresql.log'})",
        cwd=directory,
    )  # fmt: skip


def stop_postgres(binaries: Path, data: Path, account, directory: Path) -> bool:
    """Stop the cluster (fast shutdown: open sessions are rolled back); whether it was running."""
    if not postgres_running(binaries, data, account, directory):
        return False
    run_checked(
        as_account([str(binaries / "pg_ctl"), "stop", "--pgdata", str(data), "--mode", "fast", "--wait"], account),
        "stopping PostgreSQL",
        cwd=directory,
    )
    return True


def create_databases(port: int, password_file: Path) -> None:
    """Create the ``mlflow`` and ``optuna`` databases when missing."""
    import psycopg2

    password = password_file.read_text().strip().rsplit(":", 1)[1]
    connection = psycopg2.connect(
        host=LOOPBACK, port=port, user=DATABASE_ROLE, password=password, dbname="postgres", connect_timeout=30
    )
    try:
        connection.autocommit = True  # CREATE DATABASE cannot run inside a transaction
        with connection.cursor() as cursor:
            for name in (DATABASE, SWEEP_DATABASE):
                cursor.execute("SELECT 1 FROM pg_database WHERE datname = %s", (name,))
                if cursor.fetchone() is None:
                    cursor.execute(f'CREATE DATABASE "{name}"')
    finally:
        connection.close()


def backend_store_uri(port: int, database: str = DATABASE) -> str:
    """The SQLAlchemy URI of a database; the password comes from ``PGPASSFILE``, never the command line."""
    return f"postgresql://{DATABASE_ROLE}@{LOOPBACK}:{port}/{database}"


def server_marker(state: dict) -> str:
    """What the MLflow server's command line contains: its port option."""
    return f"--port {state.get('port')} "


def mlflow_running(state: dict) -> bool:
    """Whether the server recorded in ``state`` is alive and answers ``/health``."""
    pid = state.get("mlflow_pid")
    return process_alive(pid, server_marker(state)) and answers(f"{state['url']}/health")


def client_host(host: str) -> str:
    """The address clients on this machine use for a server bound to ``host``."""
    return LOOPBACK if host in ("0.0.0.0", "") else host


def start(arguments: argparse.Namespace) -> None:
    """Bring up whatever of PostgreSQL, the database and the MLflow server is not running."""
    if not arguments.dir:
        fail("--dir is empty: name the directory that keeps the database and artifacts, e.g. DIR=/srv/carp-tracking")
    directory = Path(arguments.dir).expanduser().absolute()
    state_path = directory / STATE_FILE
    state = read_state(state_path)
    binaries = find_postgres_binaries(arguments.pg_bin)
    account = database_account(arguments.db_user or state.get("db_user"))
    data = directory / "postgres"
    password_file = directory / "pgpass"
    destination = arguments.artifacts_destination or state.get("artifacts_destination")
    destination = destination or (directory / "artifacts").as_uri()
    if "://" not in destination:  # a plain path: absolute, so that a restart from elsewhere finds the same one
        destination = Path(destination).expanduser().absolute().as_uri()
    port = arguments.port if arguments.port is not None else state.get("port", 5000)

    if mlflow_running(state):
        if port not in (0, state["port"]) or destination != state["artifacts_destination"]:
            fail(
                f"the tracking server in {directory} already runs at {state['url']} with artifacts in "
                f"{state['artifacts_destination']}: stop it first to change its port or artifact store"
            )
        create_databases(state["db_port"], password_file)
        print(f"MLflow tracking server already running at {state['url']}")
        return

    # Everything that can refuse is checked before anything is created.
    if port == 0:
        port = free_port(client_host(arguments.host))
    require_free_port(port, arguments.host, "the MLflow server", "--port (PORT=...)")
    db_port = arguments.db_port or state.get("db_port") or free_port()
    database_up = (data / "PG_VERSION").exists() and postgres_running(binaries, data, account, directory)
    if database_up and arguments.db_port and arguments.db_port != state.get("db_port"):
        fail(f"PostgreSQL in {data} already runs on port {state.get('db_port')}: stop it first to change --db-port")
    if not database_up:
        require_free_port(db_port, LOOPBACK, "PostgreSQL", "--db-port")
    check_reachable(directory, account)
    directory = prepare_directory(arguments.dir, "--dir")

    if not (data / "PG_VERSION").exists():
        if data.exists() and any(data.iterdir()):
            fail(f"{data}: exists but holds no PostgreSQL cluster; remove it or choose another --dir")
        if data.exists():
            data.rmdir()
        password_file.write_text(f"{LOOPBACK}:*:*:{DATABASE_ROLE}:{secrets.token_hex(24)}\n")
        password_file.chmod(0o600)
        initialize_cluster(binaries, data, account, password_file, directory)
    elif not password_file.exists():
        fail(f"{password_file}: missing, so the database's password is lost; remove {data} to start a new cluster")
    # Saved before the database starts, so that `stop` finds it even when a later step fails.
    state = {
        **state,
        "db_port": db_port,
        "db_user": account.pw_name if account else None,
        "pg_bin": str(binaries),
        "mlflow_pid": None,
    }
    write_state(state_path, state)
    if not database_up:
        start_postgres(binaries, data, account, db_port, directory)
    create_databases(db_port, password_file)

    url = f"http://{client_host(arguments.host)}:{port}"
    command = [
        sys.executable, "-m", "mlflow", "server",
        "--backend-store-uri", backend_store_uri(db_port),
        "--artifacts-destination", destination,
        "--host", arguments.host,
        "--port", str(port),
        "--workers", str(arguments.workers),
    ]  # fmt: skip
    if arguments.allowed_hosts:
        command += ["--allowed-hosts", arguments.allowed_hosts]
    if destination.startswith("file://"):
        Path(destination.removeprefix("file://")).mkdir(parents=True, exist_ok=True)
    log_path = directory / "mlflow.log"
    environment = {**os.environ, "PGPASSFILE": str(password_file)}
    server = start_detached(command, log_path, env=environment, cwd=directory)
    state.update(url=url, host=arguments.host, port=port, artifacts_destination=destination, mlflow_pid=server.pid)
    write_state(state_path, state)
    wait_or_stop(lambda: answers(f"{url}/health"), STARTUP_SECONDS, server, log_path, "the MLflow server")
    print(f"MLflow tracking server at {url} (PostgreSQL on {LOOPBACK}:{db_port}, artifacts in {destination})")
    print(f"point carp at it with the param  tracking.uri: {url}")
    print_sweep_storage(db_port, password_file)


def print_sweep_storage(db_port: int, password_file: Path) -> None:
    """Tell how sweep workers reach the ``optuna`` database."""
    print(
        f"sweep workers on this machine: sweep.storage: {backend_store_uri(db_port, SWEEP_DATABASE)} "
        f"with PGPASSFILE={password_file}"
    )


def stop(arguments: argparse.Namespace) -> None:
    """Stop the MLflow server, then PostgreSQL; a service already down is skipped."""
    state_path, state = saved_state(arguments.dir, STATE_FILE, "tracking server")
    directory = state_path.parent
    stopped_server = stop_recorded(state_path, state, "mlflow_pid", server_marker(state))
    binaries = Path(state["pg_bin"])
    account = pwd.getpwnam(state["db_user"]) if state.get("db_user") else None
    stopped_database = stop_postgres(binaries, directory / "postgres", account, directory)
    print(
        f"MLflow server {'stopped' if stopped_server else 'was not running'}; "
        f"PostgreSQL {'stopped' if stopped_database else 'was not running'}"
    )


def status(arguments: argparse.Namespace) -> None:
    """Print the server's URL and exit 0 when it answers, else say so and exit 3."""
    directory = Path(arguments.dir).expanduser().absolute()
    state = read_state(directory / STATE_FILE)
    if state and mlflow_running(state):
        print(state["url"])
        return
    print(f"no tracking server answers in {directory} (its log: {directory / 'mlflow.log'})")
    sys.exit(3)


def sweep_storage(arguments: argparse.Namespace) -> None:
    """Print the ``sweep.storage`` URL of the cluster's ``optuna`` database, else say why not and exit 3."""
    directory = Path(arguments.dir).expanduser().absolute()
    state = read_state(directory / "tracking.json")
    if not state.get("db_port"):
        print(f"no database was started in {directory}")
        sys.exit(3)
    print(backend_store_uri(state["db_port"], SWEEP_DATABASE))


def main() -> None:
    """Parse the command line and run the subcommand."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    start_parser = commands.add_parser("start", help="start PostgreSQL and the MLflow server (idempotent)")
    start_parser.add_argument("--dir", required=True, help="directory for the cluster, artifacts, logs and state")
    start_parser.add_argument("--port", type=int, help="MLflow server port (default 5000, 0: any free port)")
    start_parser.add_argument("--host", default=LOOPBACK, help="address the MLflow server binds (default loopback)")
    start_parser.add_argument("--db-port", type=int, help="PostgreSQL port on 127.0.0.1 (default: a free one)")
    start_parser.add_argument("--artifacts-destination", help="artifact store URI (default file://DIR/artifacts)")
    start_parser.add_argument("--workers", type=int, default=2, help="MLflow server worker processes")
    start_parser.add_argument("--allowed-hosts", help="Host headers MLflow accepts beyond localhost and private IPs")
    start_parser.add_argument("--pg-bin", help="directory of initdb and pg_ctl (default: found)")
    start_parser.add_argument("--db-user", help="account that runs PostgreSQL when started by root")
    for name, help_text in (
        ("stop", "stop the MLflow server and PostgreSQL"),
        ("status", "print the server URL"),
        ("sweep-storage", "print the sweep.storage URL of the optuna database"),
    ):
        commands.add_parser(name, help=help_text).add_argument("--dir", required=True)
    arguments = parser.parse_args()
    {"start": start, "stop": stop, "status": status, "sweep-storage": sweep_storage}[arguments.command](arguments)


if __name__ == "__main__":
    main()
