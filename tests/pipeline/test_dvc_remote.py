"""`tools/dvc_remote.py`: what it writes into `.dvc/config` and what it refuses (push, pull: test_shared_services)."""

import subprocess
import sys

import pytest

from tests.services import tool


@pytest.fixture
def project(tmp_path):
    directory = tmp_path / "project"
    directory.mkdir()
    subprocess.run([sys.executable, "-m", "dvc", "init", "--no-scm", "-q"], cwd=directory, check=True)
    return directory


def configure(project, *arguments):
    return tool("dvc_remote.py", *arguments, "--project", str(project), timeout=120)


def test_a_new_url_replaces_the_remote_and_drops_the_old_endpoint(project, tmp_path):
    first = configure(project, "s3://bucket/carp", "--endpoint-url", "http://127.0.0.1:8333")
    assert first.returncode == 0, first.stderr
    config = (project / ".dvc/config").read_text()
    assert "remote = shared" in config and "url = s3://bucket/carp" in config
    assert "endpointurl = http://127.0.0.1:8333" in config

    share = tmp_path / "share" / "dvc"
    second = configure(project, str(share))
    assert second.returncode == 0, second.stderr
    config = (project / ".dvc/config").read_text()
    assert f"url = {share}" in config and "endpointurl" not in config and "s3://" not in config
    assert share.is_dir()


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (("relative/dir",), "URL=relative/dir: a directory remote must be an absolute path"),
        (("gs://bucket/carp",), "URL=gs://bucket/carp: only a directory path or s3:// is set up here"),
        (("s3://",), "URL=s3://: names no bucket"),
        (
            ("/tmp/x", "--endpoint-url", "http://h:1"),
            "--endpoint-url=http://h:1: only an s3:// remote takes an endpoint",
        ),
        (("",), "URL is empty"),
    ],
)
def test_bad_urls_are_refused_with_one_line_and_nothing_written(project, arguments, message):
    config_before = (project / ".dvc/config").read_text()
    refused = configure(project, *arguments)
    lines = refused.stderr.splitlines()
    assert refused.returncode == 1 and len(lines) == 1 and lines[0].startswith(f"error: {message}"), refused.stderr
    assert (project / ".dvc/config").read_text() == config_before


def test_a_directory_that_is_no_dvc_project_is_refused(tmp_path):
    refused = tool("dvc_remote.py", "/tmp/x", "--project", str(tmp_path), timeout=60)
    assert refused.returncode == 1
    assert refused.stderr.strip() == f"error: --project={tmp_path}: not a DVC project (no .dvc directory)"
