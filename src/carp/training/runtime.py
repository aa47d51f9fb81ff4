"""Run-time setup shared by the trainers: device, training precision, seeding and the C allocator."""

import contextlib
import ctypes
import platform
import random

import numpy as np
import torch

from carp.config import TRAINING_PRECISIONS


def resolve_device(device: str) -> torch.device:
    """Map "auto" to cuda when available, else cpu; pass any other torch device string through."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def cpu_multiplies_bfloat16() -> bool:
    """True when this CPU has native bfloat16 matrix instructions (AMX or AVX512-BF16), which oneDNN uses."""
    # Private helpers of torch.cpu (present in the pinned torch); without them, assume emulated bfloat16.
    checks = (getattr(torch.cpu, "_is_amx_tile_supported", None), getattr(torch.cpu, "_is_avx512_bf16_supported", None))
    return any(check is not None and check() for check in checks)


def resolve_precision(precision: str, device: torch.device) -> torch.dtype:
    """The autocast dtype of training steps: `precision` ("auto", "float32" or "bfloat16") on `device`.

    "auto" picks bfloat16 where the hardware multiplies it natively, float32 elsewhere: emulated bfloat16 matmuls
    are several times slower than float32 ones. Measured on this project's 2-core AMX CPU, a batch-256 training step
    of the default policy takes 0.77x the float32 time with bfloat16 autocast (`benchmarks/policy_speed.py`).
    """
    if precision not in TRAINING_PRECISIONS:
        raise ValueError(f"precision must be one of {TRAINING_PRECISIONS}, got {precision!r}")
    if precision == "auto":
        if device.type == "cuda":
            native = torch.cuda.is_bf16_supported()
        else:
            native = device.type == "cpu" and cpu_multiplies_bfloat16()
        return torch.bfloat16 if native else torch.float32
    return torch.bfloat16 if precision == "bfloat16" else torch.float32


def precision_name(dtype: torch.dtype) -> str:
    """Name of a resolved precision as params, logs and MLflow tags write it: "float32" or "bfloat16"."""
    return str(dtype).removeprefix("torch.")


def autocast_to(dtype: torch.dtype, device: torch.device) -> contextlib.AbstractContextManager:
    """Autocast to `dtype` on `device` for a training forward pass; a no-op context for float32."""
    if dtype == torch.float32:
        return contextlib.nullcontext()
    return torch.autocast(device_type=device.type, dtype=dtype)


def seed_everything(seed: int) -> None:
    """Seed torch, numpy's global generator and Python's ``random``."""
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)
    random.seed(seed)


# glibc's mallopt parameters (malloc.h) and the values `keep_freed_memory` sets.
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_MMAP_THRESHOLD_BYTES = 32 << 20  # above every tensor of a tokenizer training step at the default sizes
_TRIM_THRESHOLD_BYTES = 256 << 20


def keep_freed_memory() -> bool:
    """Let this process reuse freed tensor memory instead of handing it back to the OS and faulting it in again.

    With its default settings glibc serves each allocation above 128 KiB with fresh pages from `mmap` and unmaps them
    on free, and returns free memory at the top of the heap to the OS. A training step of the vectorized tokenizer
    (A = 10, batch 64) allocates dozens of 0.1-1 MB tensors, so every step faulted in ~2,300 new pages: 5.5 ms of
    system time in a ~29 ms step (`resource.getrusage`, one thread, AVX-512 machine), while a single-dimension
    module's tensors stay below the threshold (2 faults per step). Raising both thresholds (allocations up to 32 MB
    from the heap, up to 256 MB of free heap kept) brings the faults to zero; the cost is that memory freed by the
    process is reused by it rather than returned to the system.

    Process-wide and permanent, so it belongs in entry points (stage scripts, benchmarks), not in library functions.
    Returns True if applied, False where the C library is not glibc (the setting is then left alone).
    """
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    libc = ctypes.CDLL(None)
    applied = libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_BYTES) == 1
    return libc.mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD_BYTES) == 1 and applied
