import logging
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


@pytest.fixture
def served_settings(monkeypatch):
    """The settings `carp serve` would serve with; nothing is served."""
    from carp.serving import startup

    settings = []
    monkeypatch.setattr(startup, "serve_forever", lambda server: settings.append(server.settings))
    monkeypatch.delenv("CARP_SERVE_TOKEN", raising=False)
    return settings


def test_the_token_comes_from_a_file_or_the_environment_and_the_flag_warns(
    tmp_path, served_settings, monkeypatch, caplog
):
    from carp import cli

    model = str(save_tiny_checkpoint(tmp_path / "policy.pt"))
    token_file = tmp_path / "token"
    token_file.write_text("from-file\n")
    cli.main(["serve", "--model", model, "--backend", "torch", "--token-file", str(token_file)])
    monkeypatch.setenv("CARP_SERVE_TOKEN", "from-environment")
    cli.main(["serve", "--model", model, "--backend", "torch"])
    with caplog.at_level(logging.WARNING, logger="carp.cli"):
        cli.main(["serve", "--model", model, "--backend", "torch", "--token", "from-flag"])
    assert [settings.token for settings in served_settings] == ["from-file", "from-environment", "from-flag"]
    assert any("visible to every local user in the process list" in record.getMessage() for record in caplog.records)


def test_prediction_settings_come_from_a_flag_else_the_params_serving_section(tmp_path, served_settings):
    from carp import cli

    model = str(save_tiny_checkpoint(tmp_path / "policy.pt"))
    params = tmp_path / "params.yaml"
    params.write_text("serving: {max_batch: 4, batch_window_ms: 20, prediction_threads: 3}\n")
    cli.main(["serve", "--model", model, "--backend", "torch"])
    cli.main(["serve", "--model", model, "--backend", "torch", "--params", str(params)])
    cli.main(["serve", "--model", model, "--backend", "torch", "--params", str(params), "--max-batch", "2"])
    chosen = [(s.max_batch_size, s.batch_window_s, s.prediction_threads) for s in served_settings]
    assert chosen == [(1, 0.0, 0), (4, 0.02, 3), (2, 0.02, 3)]


@pytest.mark.parametrize(
    "arguments, message",
    [
        (["--host", "0.0.0.0"], "error: host '0.0.0.0' is reachable from other machines: set a token"),
        (["--tls-cert", "missing.pem"], "error: tls: missing.pem: no such file"),
        (["--token-file", "missing-token"], "error: missing-token: no such token file"),
        (["--batch-window-ms", "5000"], "error: serving.batch_window_ms=5000.0: must be between 0 and 1000"),
    ],
)
def test_unsafe_or_broken_serving_settings_print_one_error_line(tmp_path, served_settings, capsys, arguments, message):
    from carp import cli

    model = str(save_tiny_checkpoint(tmp_path / "policy.pt"))
    with pytest.raises(SystemExit) as exited:
        cli.main(["serve", "--model", model, "--backend", "torch", *arguments])
    assert exited.value.code == 1 and served_settings == []
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(message), lines


def test_a_non_loopback_host_serves_without_a_token_only_when_told_to(tmp_path, served_settings):
    from carp import cli

    model = str(save_tiny_checkpoint(tmp_path / "policy.pt"))
    cli.main(["serve", "--model", model, "--backend", "torch", "--host", "0.0.0.0", "--allow-no-token"])
    assert served_settings[0].host == "0.0.0.0" and served_settings[0].token is None
