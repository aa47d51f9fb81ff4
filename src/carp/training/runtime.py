"""Run-time setup shared by the trainers: device, training precision and seeding."""

import contextlib
import random

import numpy as np
import torch

from carp.config.checks import TRAINING_PRECISIONS


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
    are several times slower than float32 ones, while native ones (AMX on the CPU) make a training step faster than
    float32 (`benchmarks/policy_speed.py` times both).
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
