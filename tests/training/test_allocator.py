"""`keep_freed_memory`: a vectorized tokenizer training step reuses freed memory instead of faulting in new pages."""

import platform
import subprocess
import sys

import pytest

# Ten training steps of the A = 10 tokenizer at batch 64 (after three warm-up steps); prints the minor page faults
# per step. Run in a fresh interpreter because the allocator setting is process-wide and permanent.
FAULT_COUNTER = """
import resource, sys, torch
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer
from carp.training.runtime import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "keep" else None
torch.set_num_threads(1)
torch.manual_seed(0)
tokenizer = MultiScaleActionTokenizer(TokenizerSpec(action_dim=10))
optimizer = torch.optim.AdamW(tokenizer.parameters(), lr=1e-3)
batch = torch.rand(64, 16, 10) * 2 - 1
def step():
    optimizer.zero_grad(set_to_none=True)
    tokenizer(batch).loss.backward()
    optimizer.step()
for _ in range(3):
    step()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    step()
print(applied, (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 10)
"""


def faults_per_step(mode: str) -> tuple[str, float]:
    applied, faults = subprocess.run(
        [sys.executable, "-c", FAULT_COUNTER, mode], capture_output=True, text=True, check=True
    ).stdout.split()
    return applied, float(faults)


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="tunes glibc's allocator")
def test_keeping_freed_memory_removes_the_page_faults_of_tokenizer_steps():
    applied, kept = faults_per_step("keep")
    _, default = faults_per_step("default")
    assert applied == "True"
    # With glibc's defaults the step's 0.1-1 MB tensors are mapped afresh (~2,300 faults per step measured).
    assert default > 500
    assert kept < default / 20
