import shlex

from carp.config import SweepConfig
from carp.sweep.space import (
    TrialSettings,
    all_settings,
    codebook_choices,
    parse_schedule_label,
    scale_choices,
    schedule_label,
)


def test_search_space_follows_the_config_order():
    config = SweepConfig(scale_schedules=((4,), (1, 2, 4)), codebook_sizes=(64, 8))
    assert scale_choices(config) == ["[4]", "[1,2,4]"]
    assert codebook_choices(config) == [64, 8]
    grid = all_settings(config)
    assert len(grid) == 4 and len(set(grid)) == 4
    assert grid[0] == TrialSettings((4,), 64) and grid[-1] == TrialSettings((1, 2, 4), 8)


def test_schedule_label_round_trip():
    for scales in [(4,), (1, 4), (1, 2, 3, 4)]:
        assert parse_schedule_label(schedule_label(scales)) == scales
    assert " " not in schedule_label((1, 2, 4))


def test_set_arguments_and_shell_quoting():
    settings = TrialSettings((1, 2, 4), 256)
    assert settings.num_scales == 3
    assert settings.set_arguments() == ["scales=[1,2,4]", "codebook_size=256"]
    assert settings.command_line() == "-S 'scales=[1,2,4]' -S codebook_size=256"
    # What a shell hands to `dvc exp run` is exactly the argument list.
    assert shlex.split(settings.command_line()) == ["-S", "scales=[1,2,4]", "-S", "codebook_size=256"]
