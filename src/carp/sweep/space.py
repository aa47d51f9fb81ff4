"""The sweep's search space: scale schedules ``s_1 < ... < s_K`` crossed with codebook sizes ``V``.

Optuna's categorical choices must be plain scalars, so a schedule is stored as its ``-S`` spelling (``[1,2,4]``);
that spelling is also what a trial passes to ``dvc exp run -S scales=[1,2,4]``.
"""

import itertools
import json
import shlex
from dataclasses import dataclass

from carp.config.experiments import SweepConfig

SCALES_PARAM = "scales"
CODEBOOK_PARAM = "codebook_size"


@dataclass(frozen=True)
class TrialSettings:
    """The two swept params of one trial.

    Attributes:
        scales: tokens per dimension at each scale, ``(s_1, ..., s_K)``, strictly increasing.
        codebook_size: ``V``, codes per action dimension.
    """

    scales: tuple[int, ...]
    codebook_size: int

    @property
    def num_scales(self) -> int:
        """``K``."""
        return len(self.scales)

    def set_arguments(self) -> list[str]:
        """Values for ``dvc exp run -S`` (one list item per ``-S``), e.g. ``["scales=[1,2,4]", "codebook_size=64"]``."""
        return [f"{SCALES_PARAM}={schedule_label(self.scales)}", f"{CODEBOOK_PARAM}={self.codebook_size}"]

    def command_line(self) -> str:
        """The ``-S`` arguments quoted for a POSIX shell: ``-S 'scales=[1,2,4]' -S codebook_size=64``."""
        return " ".join(f"-S {shlex.quote(argument)}" for argument in self.set_arguments())


def schedule_label(scales: tuple[int, ...]) -> str:
    """``(1, 2, 4)`` -> ``[1,2,4]`` (no spaces, so it survives unquoted argument lists and CSV cells)."""
    return "[" + ",".join(str(scale) for scale in scales) + "]"


def point_key(settings: TrialSettings) -> str:
    """The grid point's key in the claims table, e.g. ``scales=[1,2,4] codebook_size=64``."""
    return " ".join(settings.set_arguments())


def parse_schedule_label(label: str) -> tuple[int, ...]:
    """Inverse of :func:`schedule_label`."""
    return tuple(int(scale) for scale in json.loads(label))


def scale_choices(config: SweepConfig) -> list[str]:
    """Categorical choices for ``scales`` in the order of ``sweep.scale_schedules``."""
    return [schedule_label(schedule) for schedule in config.scale_schedules]


def codebook_choices(config: SweepConfig) -> list[int]:
    """Categorical choices for ``codebook_size`` in the order of ``sweep.codebook_sizes``."""
    return list(config.codebook_sizes)


def all_settings(config: SweepConfig) -> list[TrialSettings]:
    """Every point of the grid (schedules x codebook sizes); its length bounds how many distinct trials exist."""
    return [
        TrialSettings(tuple(schedule), size)
        for schedule, size in itertools.product(config.scale_schedules, config.codebook_sizes)
    ]
