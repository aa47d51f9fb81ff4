"""Run-time setup shared by the trainers: device choice and seeding."""

import random

import numpy as np
import torch


def resolve_device(device: str) -> torch.device:
    """Map "auto" to cuda when available, else cpu; pass any other torch device string through."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def seed_everything(seed: int) -> None:
    """Seed torch, numpy's global generator and Python's ``random``."""
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)
    random.seed(seed)
