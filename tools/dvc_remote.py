"""Make a shared directory or an S3 bucket the project's default DVC remote.

    python tools/dvc_remote.py URL [--endpoint-url URL] [--name shared] [--project DIR]

``URL`` is an absolute directory path (a local disk or an NFS share mounted at the same path on every machine) or
``s3://bucket/prefix`` (AWS S3, or an S3-compatible store such as MinIO or SeaweedFS with ``--endpoint-url``). The
remote is written to the project's ``.dvc/config``, which is committed, so every clone pushes to and pulls from it.
S3 credentials are never written: DVC takes them from ``AWS_ACCESS_KEY_ID`` / ``AWS_SECRET_ACCESS_KEY`` or
``~/.aws`` on each machine. Running it again with another URL replaces the remote.

After a run: ``dvc push``; on another machine: ``git clone``, ``dvc pull``, and ``dvc repro`` finds every stage
up to date.
"""

import argparse
import os
import subprocess
import sys
from pathlib import Path

from service_support import fail


def run_dvc(arguments: list[str], project: Path) -> None:
    """Run ``dvc ARGUMENTS`` in the project; fail with DVC's own message when it refuses."""
    completed = subprocess.run([sys.executable, "-m", "dvc", *arguments], cwd=project, capture_output=True, text=True)
    if completed.returncode != 0:
        message = " ".join((completed.stderr or completed.stdout).split())
        fail(f"dvc {' '.join(arguments[:2])}: {message}")


def check_directory(url: str) -> None:
    """A directory remote must be an absolute path that this machine can create and write."""
    path = Path(url)
    if not path.is_absolute():
        fail(f"URL={url}: a directory remote must be an absolute path (the same mount path on every machine)")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        fail(f"URL={url}: cannot create the directory ({error.strerror})")
    if not os.access(path, os.W_OK | os.X_OK):
        fail(f"URL={url}: the directory is not writable by this user")


def main() -> None:
    """Check the URL and write the remote into .dvc/config."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("url", help="absolute directory path or s3://bucket/prefix")
    parser.add_argument("--endpoint-url", help="S3-compatible endpoint, e.g. http://storage.lab:8333")
    parser.add_argument("--name", default="shared", help="the remote's name in .dvc/config")
    parser.add_argument("--project", type=Path, default=Path.cwd(), help="the DVC project (default: here)")
    arguments = parser.parse_args()
    project = arguments.project.absolute()
    url = arguments.url
    if not (project / ".dvc").is_dir():
        fail(f"--project={project}: not a DVC project (no .dvc directory)")
    if not url:
        fail("URL is empty: name a shared directory (URL=/mnt/share/carp-dvc) or a bucket (URL=s3://bucket/carp)")
    if arguments.endpoint_url and not url.startswith("s3://"):
        fail(f"--endpoint-url={arguments.endpoint_url}: only an s3:// remote takes an endpoint")
    if url.startswith("s3://"):
        if len(url.removeprefix("s3://").strip("/")) == 0:
            fail(f"URL={url}: names no bucket")
    elif "://" in url:
        fail(f"URL={url}: only a directory path or s3:// is set up here; see `dvc remote add --help` for others")
    else:
        check_directory(url)

    # `--force` rewrites the remote's whole section, so an endpoint set for an earlier URL goes with it.
    run_dvc(["remote", "add", "--default", "--force", arguments.name, url], project)
    if arguments.endpoint_url:
        run_dvc(["remote", "modify", arguments.name, "endpointurl", arguments.endpoint_url], project)
    where = f" at {arguments.endpoint_url}" if arguments.endpoint_url else ""
    print(f"DVC remote '{arguments.name}' -> {url}{where} is the default (in .dvc/config: commit it)")
    print("push after a run: dvc push; on another machine: git clone ..., dvc pull, dvc repro")


if __name__ == "__main__":
    main()
