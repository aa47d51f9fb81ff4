import math

import pytest

from carp.evaluation.metrics import latency_summary, measure_summary, task_score, wilson_interval


@pytest.mark.parametrize(
    ("successes", "trials", "expected"),
    [
        # Reference values of the Wilson score interval at 95% (z = 1.959964).
        (45, 50, (0.7864, 0.9565)),
        (50, 50, (0.9287, 1.0)),
        (0, 50, (0.0, 0.0713)),
        (25, 50, (0.3664, 0.6336)),
        (1, 10, (0.0179, 0.4042)),
    ],
)
def test_wilson_interval_matches_reference_values(successes, trials, expected):
    lower, upper = wilson_interval(successes, trials)
    assert lower == pytest.approx(expected[0], abs=1e-4)
    assert upper == pytest.approx(expected[1], abs=1e-4)


def test_wilson_interval_contains_the_estimate_and_rejects_bad_counts():
    lower, upper = wilson_interval(7, 9)
    assert lower < 7 / 9 < upper
    assert wilson_interval(0, 0) == (0.0, 1.0)
    with pytest.raises(ValueError, match="successes=5 must lie in"):
        wilson_interval(5, 3)


def test_latency_summary_in_milliseconds():
    summary = latency_summary([0.001 * i for i in range(1, 11)], "predict")
    assert summary["predict_ms_median"] == pytest.approx(5.5)
    assert summary["predict_ms_p90"] == pytest.approx(9.1)
    assert math.isnan(latency_summary([], "decode")["decode_ms_median"])


def test_measure_summary_averages_each_measure_over_the_episodes_that_measured_it():
    nan = float("nan")
    measures = [
        {"insertion_offset_mm": 4.0, "insertion_contact_step": 30.0},
        {"insertion_offset_mm": 6.0, "insertion_contact_step": 35.0},
        {"insertion_offset_mm": 11.0, "insertion_contact_step": 40.0},
        {"insertion_offset_mm": nan, "insertion_contact_step": nan},  # no contact
        {},  # a worker that died records no measure
    ]
    summary = measure_summary(measures)
    assert summary["insertion_offset_mm_mean"] == 7.0
    assert summary["insertion_offset_mm_variance"] == pytest.approx(13.0)  # (9 + 1 + 16) / (3 - 1)
    assert summary["insertion_offset_mm_episodes"] == 3
    assert summary["insertion_contact_step_mean"] == 35.0 and summary["insertion_contact_step_variance"] == 25.0
    assert list(summary) == [
        f"{name}_{statistic}"
        for name in ("insertion_offset_mm", "insertion_contact_step")
        for statistic in ("mean", "variance", "episodes")
    ]


def test_measure_summary_of_too_few_values_is_nan_and_of_no_measures_empty():
    one = measure_summary([{"insertion_offset_mm": 5.0}, {"insertion_offset_mm": float("nan")}])
    assert one["insertion_offset_mm_mean"] == 5.0 and math.isnan(one["insertion_offset_mm_variance"])
    assert one["insertion_offset_mm_episodes"] == 1
    none = measure_summary([{"insertion_offset_mm": float("nan")}])
    assert math.isnan(none["insertion_offset_mm_mean"]) and none["insertion_offset_mm_episodes"] == 0
    assert measure_summary([{}, {}]) == {} and measure_summary([]) == {}


def test_a_tasks_score_is_its_score_measure_or_else_its_success_rate():
    summary = {"success_rate": 0.2, **measure_summary([{"max_reward": 0.5}, {"max_reward": 1.0}])}
    assert task_score(summary, "max_reward") == pytest.approx(0.75)
    assert task_score(summary, None) == 0.2
    assert math.isnan(task_score({"success_rate": 0.0}, "max_reward"))  # no episode measured it
