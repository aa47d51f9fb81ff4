import subprocess
import sys
import textwrap

from carp.evaluation.scratch import remove_abandoned_scratch, scratch_directory

# Enters a scratch directory under argv[1], prints it, then either waits for its stdin to close or kills itself.
HOLDER = textwrap.dedent(
    """
    import os, signal, sys
    from pathlib import Path
    from carp.evaluation.scratch import scratch_directory

    with scratch_directory(Path(sys.argv[1])) as directory:
        (directory / "graph.onnx").write_bytes(b"graph")
        print(directory, flush=True)
        if sys.argv[2] == "kill":
            os.kill(os.getpid(), signal.SIGKILL)
        sys.stdin.read()
    """
)


def _holder(root, how: str) -> tuple[subprocess.Popen, str]:
    process = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(root), how], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    return process, process.stdout.readline().strip()


def test_a_killed_process_leaves_a_directory_that_the_next_one_removes_and_a_live_one_keeps_its_own(tmp_path):
    killed, killed_directory = _holder(tmp_path, "kill")
    assert killed.wait(timeout=60) < 0
    # The killed process never reached the end of its `with` block; its directory is still there.
    assert (tmp_path / killed_directory / "graph.onnx").exists()
    foreign = tmp_path / "carp-onnx-not-ours"
    foreign.mkdir()
    live, live_directory = _holder(tmp_path, "wait")
    try:
        # The next scratch directory (here another process's) removed it; a directory without a lock is not ours.
        assert not (tmp_path / killed_directory).exists() and foreign.is_dir()
        with scratch_directory(tmp_path) as directory:
            assert (tmp_path / live_directory / "graph.onnx").exists(), "a running process keeps its directory"
            assert directory.is_dir() and directory.name.startswith("carp-onnx-")
        assert not directory.exists()
    finally:
        live.stdin.close()
        assert live.wait(timeout=60) == 0
    # A process that ends normally cleans up after itself; nothing is left to remove.
    assert not (tmp_path / live_directory).exists()
    assert remove_abandoned_scratch(tmp_path) == []
