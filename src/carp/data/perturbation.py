"""Correlated perturbations of a scripted expert's executed actions (DART-style noise injection).

A scripted expert replays one smooth path per initial state, so its demonstrations never show the arm off that path
and a policy that drifts by a centimetre meets states it has not seen. Collecting with noise fixes that: the env
executes the expert's commanded pose displaced by a slowly varying offset, while the file records the expert's clean
command. Each demo then shows the arm away from the plan together with the action that brings it back.

The offset follows a first-order autoregressive process per axis,
``offset_t = rho * offset_{t-1} + sqrt(1 - rho**2) * sigma * noise_t``, whose stationary standard deviation is
``sigma`` and whose correlation time is about ``1 / (1 - rho)`` control steps. It is driven only while the expert
moves in free space; during contact phases (descending to grasp, closing or opening the gripper, placing) it decays
by ``contact_decay`` per step, so grasps and placements stay as precise as without noise.
"""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ExpertNoise:
    """Size and timing of the executed-action offset.

    Attributes:
        position_m: stationary standard deviation of the position offset per axis (m); 0 disables it.
        rotation_rad: stationary standard deviation of the orientation offset per axis (rad, axis-angle); 0 disables.
        correlation: per-step autocorrelation ``rho`` of the offset in free space (0.9: ~10 steps = 0.5 s at 20 Hz).
        contact_decay: per-step factor applied to the offset outside free space.
    """

    position_m: float = 0.0
    rotation_rad: float = 0.0
    correlation: float = 0.9
    contact_decay: float = 0.7

    def __post_init__(self) -> None:
        if self.position_m < 0 or self.rotation_rad < 0:
            raise ValueError(f"noise sizes must be >= 0, got {self.position_m} m and {self.rotation_rad} rad")
        if not 0.0 <= self.correlation < 1.0 or not 0.0 <= self.contact_decay < 1.0:
            raise ValueError(
                f"correlation and contact_decay must be in [0, 1), got {self.correlation} and {self.contact_decay}"
            )

    @property
    def enabled(self) -> bool:
        """Whether any offset is drawn."""
        return self.position_m > 0 or self.rotation_rad > 0


class CorrelatedOffset:
    """One episode's offset process; call :meth:`step` once per control step.

    Args:
        noise: sizes and timing.
        rng: the episode's generator (seed it from the episode seed for reproducible demos).
    """

    def __init__(self, noise: ExpertNoise, rng: np.random.Generator) -> None:
        self.noise = noise
        self.rng = rng
        self.scale = np.array([noise.position_m] * 3 + [noise.rotation_rad] * 3)
        self.offset = np.zeros(6)

    def step(self, driven: bool) -> tuple[np.ndarray, np.ndarray]:
        """Advance one control step; ``driven`` is False during contact phases.

        Returns:
            position offset (3,) in m and rotation offset (3,) as axis-angle in rad.
        """
        if driven:
            rho = self.noise.correlation
            innovation = self.rng.standard_normal(6) * self.scale * np.sqrt(1.0 - rho**2)
            self.offset = rho * self.offset + innovation
        else:
            self.offset = self.noise.contact_decay * self.offset
        return self.offset[:3].copy(), self.offset[3:].copy()
