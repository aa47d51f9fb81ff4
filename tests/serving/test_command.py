import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.serving.conftest import save_tiny_checkpoint

PROJECT_DIR = Path(__file__).resolve().parents[2]


def test_serve_with_a_missing_model_prints_one_error_line_and_exits_non_zero(tmp_path):
    missing = tmp_path / "nowhere" / "policy.pt"
    environment = os.environ | {"PYTHONPATH": str(PROJECT_DIR / "src")}
    result = subprocess.run(
        [sys.executable, "-m", "carp.cli", "serve", "--model", str(missing), "--params", "params.yaml"],
        cwd=PROJECT_DIR,
        env=environment,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 1
    assert result.stderr.splitlines() == [f"error: {missing}: no such model file"]
    assert result.stdout == ""


def test_register_and_serve_by_uri_without_a_usable_source_print_one_error_line(tmp_path, capsys):
    from carp import cli

    missing = tmp_path / "policy.pt"
    for argv, message in (
        (["register", "--model", str(missing)], f"error: {missing}: no such model file"),
        (["register", "--model", str(save_tiny_checkpoint(tmp_path / "p.pt")), "--alias", "latest"], "error: alias"),
    ):
        with pytest.raises(SystemExit) as exited:
            cli.main(argv)
        assert exited.value.code == 1
        lines = capsys.readouterr().err.splitlines()
        assert len(lines) == 1 and lines[0].startswith(message), lines
