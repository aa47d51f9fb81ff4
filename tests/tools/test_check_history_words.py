"""The development-history check (`tools/check_history_words.py`): what it flags, what it leaves alone, and the repo."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "tools" / "check_history_words.py"


def _load_checker():
    spec = importlib.util.spec_from_file_location("check_history_words", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


checker = _load_checker()


@pytest.mark.parametrize(
    ("text", "kind"),
    [
        ("Measured in session 18 of the benchmark.", "development round or session"),
        ("sessions 18-31 gave 3.2-3.8x", "development round or session"),
        ("the second development round tried it", "development round or session"),
        ("as this session found", "development round or session"),
        ("rounds 1-17 time the old loop", "development round or session"),
        ("fixed at commit 1e3ceb4, see d222f66", "commit hash"),
        ("9 min 24 s at 89eb75c (Lift 50/50)", "commit hash"),
        ("on the Intel machine with AMX", "named development machine"),
        ("3.7 ms on the AVX-512 machine", "named development machine"),
        ("the AMD EPYC machine ran 2x slower", "named development machine"),
        ("2.6x on the AVX2 one", "named development machine"),
        ("Intel + AMX machine", "named development machine"),
        ("an earlier probe on this machine", "named development machine"),
        ("recommended for three tasks (run E, ~3 h)", "named run"),
        ("runs A and B shared a tokenizer", "named run"),
        ("In run C, top-5 draws helped Can.", "named run"),
        ("run D's Square policy", "named run"),
        ("until 2026-11-25 it copied the layout", "date"),
        ("as of November 2026", "date"),
        ("on 25 Nov 2026", "date"),
        ("the host was slow yesterday", "date"),
        ("see docs/measurements.md", "measurement diary"),
    ],
)
def test_history_words_are_found(text, kind):
    assert kind in [found for found, _ in checker.find_in_text(text)], text


@pytest.mark.parametrize(
    "text",
    [
        "weights_sha256 = hashlib.sha256(payload).hexdigest()",
        "a sha256 of e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855 is 64 hex digits",
        "float32 and bfloat16 training; the add8 kernel",
        "Each expert is a phase machine written as a Python generator.",
        "a matmul broadcast over the batch runs B tiny products instead",
        "the loop runs A single-dimension modules",
        "run A = 1 and A = 10 in turn",
        "2-core x86 CPU, AVX-512 with AMX",
        "on CPUs without AVX-512 oneDNN falls back to im2col",
        "the benchmark takes the median of 9 rounds; single rounds spread",
        "ONNX Runtime session options: one thread",
        "episode seeds 100000-100049",
        "url: https://github.com/owner/repo/commit/1e3ceb4",
        "compare timings only on the same machine; the variants meet the same host",
        "scales [1, 2, 3, 4] with codebook_size 512",
    ],
)
def test_ordinary_prose_and_code_words_are_left_alone(text):
    assert list(checker.find_in_text(text)) == []


def test_python_files_are_checked_in_comments_and_strings_only(tmp_path):
    source = tmp_path / "module.py"
    source.write_text(
        "MAGIC = 0xdeadbeef1\n"
        "cafe1234 = 3  # an identifier that looks like a hash\n"
        "def f():\n"
        '    """Faster on the Intel machine."""\n'
        '    return "ok"  # chosen in session 4\n'
    )
    assert checker.check_file(source) == [
        f'{source}:4: named development machine: "Intel machine"',
        f'{source}:5: development round or session: "session 4"',
    ]


def test_the_script_fails_with_one_line_per_hit_and_passes_clean_files(tmp_path):
    dirty = tmp_path / "notes.md"
    dirty.write_text("# Notes\n\nMeasured at 89eb75c.\nAll good.\n")
    clean = tmp_path / "clean.yaml"
    clean.write_text("epochs: 20   # passes over the training windows; >= 1\n")
    failed = subprocess.run([sys.executable, SCRIPT, dirty, clean], capture_output=True, text=True)
    assert failed.returncode == 1
    assert failed.stdout.splitlines() == [f'{dirty}:3: commit hash: "89eb75c"']
    assert failed.stderr.startswith("error: 1 development-history word(s)")
    passed = subprocess.run([sys.executable, SCRIPT, clean], capture_output=True, text=True)
    assert (passed.returncode, passed.stdout, passed.stderr) == (0, "", "")


def test_the_repository_speaks_of_the_project_not_of_its_development():
    completed = subprocess.run([sys.executable, SCRIPT], capture_output=True, text=True, cwd=REPO)
    assert completed.returncode == 0, completed.stdout
