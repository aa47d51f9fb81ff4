"""Tiny configs of the Consistency Policy families: a two-level U-Net 16/32 wide (H a multiple of 2)."""

from carp.policies.consistency.config import ConsistencyConfig, EDMConfig

TINY_UNET = {"down_dims": (16, 32), "kernel_size": 3, "num_groups": 8, "step_embedding_dim": 16, "warmup_steps": 0}


def tiny_teacher_config(**overrides) -> EDMConfig:
    """The EDM teacher at the tiny U-Net."""
    return EDMConfig(**(TINY_UNET | overrides))


def tiny_student_config(**overrides) -> ConsistencyConfig:
    """The student at the tiny U-Net, with a 10-level discretization."""
    return ConsistencyConfig(**(TINY_UNET | {"num_levels": 10} | overrides))
