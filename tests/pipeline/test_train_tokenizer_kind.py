"""The train_tokenizer stage trains carp_msvq only and refuses another kind in one line, before reading any data."""

import subprocess
import sys
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[2]


def test_a_kind_the_pipeline_does_not_train_is_refused_in_one_line(tmp_path):
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["tokenizer"]["kind"] = "fast"
    params["policies"] = ["next_token"]
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params, sort_keys=False))
    result = subprocess.run(
        [sys.executable, str(REPO / "pipeline" / "train_tokenizer.py"), "--params", str(path)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
    )
    assert result.returncode == 1
    assert result.stderr.strip().splitlines()[-1] == (
        "error: tokenizer.kind=fast: only carp_msvq is trained by the pipeline; fast is not yet trained by the "
        "pipeline (measure it with benchmarks/tokenizer_kinds.py)"
    )
    assert len(result.stderr.strip().splitlines()) == 1
