import os
import subprocess
import sys
from pathlib import Path

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
