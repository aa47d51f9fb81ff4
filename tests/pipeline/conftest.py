"""Fixtures of the end-to-end pipeline tests."""

from pathlib import Path

import pytest

from tests.pipeline.experiment_workspaces import build_template


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> Path:
    """A workspace with ingested tiny demos, built once per module that uses it (copy it: `copy_workspace`)."""
    return build_template(tmp_path_factory.mktemp("template"))
