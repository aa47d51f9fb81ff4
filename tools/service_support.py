"""What the service scripts in ``tools/`` share: one-line errors, ports, detached processes and their state files.

A service started here runs detached in its own session (process group), so that ``stop`` ends it and everything it
started, and survives the shell that started it. Its pid, ports and settings are kept in ``<dir>/<name>.json``; a
second ``start`` reads them and does nothing when the service still answers.
"""

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

LOOPBACK = "127.0.0.1"


def fail(message: str) -> None:
    """Print a one-line error and exit with status 1."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(1)


def free_port(host: str = LOOPBACK) -> int:
    """A TCP port that nothing listens on at ``host`` right now (chosen by the kernel)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind((host, 0))
        return probe.getsockname()[1]


def port_is_free(port: int, host: str = LOOPBACK) -> bool:
    """Whether a server could listen on ``host:port`` (nothing else bound there)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        # The same option the servers set: a port whose last connection is in TIME_WAIT is free for them too.
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError:
            return False
    return True


def require_free_port(port: int, host: str, what: str, option: str) -> None:
    """Fail with one line naming ``option`` when ``host:port`` is taken."""
    if not port_is_free(port, host):
        fail(
            f"port {port} on {host} is in use by another program, so {what} cannot listen there: "
            f"pick another with {option}"
        )


def answers(url: str, timeout: float = 5.0) -> bool:
    """Whether an HTTP GET of ``url`` gets a response below 500."""
    try:
        with urllib.request.urlopen(url, timeout=timeout) as response:
            return response.status < 500
    except urllib.error.HTTPError as error:
        return error.code < 500
    except (urllib.error.URLError, ConnectionError, TimeoutError, OSError):
        return False


def process_alive(pid: int | None, marker: str) -> bool:
    """Whether ``pid`` is still the service recorded: a live process whose command line contains ``marker``.

    A pid saved before a reboot may belong to an unrelated process by now; it must never be signalled.
    """
    if not pid:
        return False
    try:
        command_line = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return False
    if marker not in command_line:
        return False
    try:
        finished, _ = os.waitpid(pid, os.WNOHANG)
    except ChildProcessError:
        return True
    return finished == 0


def start_detached(command: list[str], log_path: Path, env: dict[str, str] | None = None, cwd: Path | None = None):
    """Start ``command`` in a new session with stdout and stderr appended to ``log_path``; returns the Popen."""
    with log_path.open("a") as log:
        return subprocess.Popen(
            command,
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=subprocess.STDOUT,
            env=env,
            cwd=cwd,
            start_new_session=True,
        )


def wait_until(condition, timeout: float, process=None, log_path: Path | None = None, what: str = "service") -> None:
    """Poll ``condition()`` until true; fail with the log's tail when ``process`` exits or ``timeout`` passes."""
    deadline = time.monotonic() + timeout
    while not condition():
        if process is not None and process.poll() is not None:
            fail(f"{what} exited with status {process.returncode} while starting; its log:\n{log_tail(log_path)}")
        if time.monotonic() > deadline:
            fail(f"{what} did not answer within {timeout:.0f} s; its log:\n{log_tail(log_path)}")
        time.sleep(0.5)


def wait_or_stop(condition, timeout: float, process: subprocess.Popen, log_path: Path, what: str) -> None:
    """:func:`wait_until` for a service just started: one that fails to come up is stopped before the exit.

    A half-started service left behind would hold its ports and make the next ``start`` fail for a reason the user
    cannot see.
    """
    try:
        wait_until(condition, timeout, process, log_path, what)
    except SystemExit:
        stop_group(process.pid)
        raise


def log_tail(log_path: Path | None, characters: int = 3000) -> str:
    """The last characters of a log file (empty when there is none)."""
    if log_path is None or not log_path.exists():
        return ""
    return log_path.read_text(errors="replace")[-characters:]


def stop_group(pid: int, grace_seconds: float = 20.0) -> bool:
    """SIGTERM the process group led by ``pid``, SIGKILL it after ``grace_seconds``; whether it was running."""
    try:
        os.killpg(pid, signal.SIGTERM)
    except ProcessLookupError:
        return False
    deadline = time.monotonic() + grace_seconds
    while time.monotonic() < deadline:
        if not _group_alive(pid):
            return True
        time.sleep(0.2)
    try:
        os.killpg(pid, signal.SIGKILL)
    except ProcessLookupError:
        return True
    deadline = time.monotonic() + 10.0
    while _group_alive(pid) and time.monotonic() < deadline:
        time.sleep(0.2)
    return True


def _group_alive(group: int) -> bool:
    try:
        os.killpg(group, 0)
    except ProcessLookupError:
        return False
    try:
        os.waitpid(group, os.WNOHANG)
    except ChildProcessError:
        pass
    return True


def read_state(path: Path) -> dict:
    """The saved state of a service (``{}`` before its first start)."""
    return json.loads(path.read_text()) if path.exists() else {}


def write_state(path: Path, state: dict) -> None:
    """Save a service's state atomically."""
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_text(json.dumps(state, indent=2, sort_keys=True))
    os.replace(temporary, path)


def saved_state(directory_text: str, file_name: str, what: str) -> tuple[Path, dict]:
    """(path, state) of the service saved as ``file_name`` in ``--dir``; one-line failure when it never started."""
    state_path = Path(directory_text).expanduser().absolute() / file_name
    state = read_state(state_path)
    if not state:
        fail(f"--dir={directory_text}: no {what} was started there (no {file_name})")
    return state_path, state


def stop_recorded(state_path: Path, state: dict, pid_key: str, marker: str) -> bool:
    """Stop the process group recorded under ``state[pid_key]`` and forget its pid; whether it was running.

    ``marker`` is what the process's command line must contain (see :func:`process_alive`).
    """
    pid = state.get(pid_key)
    stopped = process_alive(pid, marker) and stop_group(pid)
    state[pid_key] = None
    write_state(state_path, state)
    return stopped


def prepare_directory(text: str, variable: str) -> Path:
    """The absolute service directory named by ``text`` (created), or a one-line error naming ``variable``."""
    if not text:
        fail(f"{variable} is empty: name the directory that keeps the service's data, e.g. {variable}=/srv/carp")
    directory = Path(text).expanduser().absolute()
    if directory.exists() and not directory.is_dir():
        fail(f"{variable}={text}: not a directory")
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        fail(f"{variable}={text}: cannot create the directory ({error.strerror})")
    return directory
