"""Per-task tokenizer metrics in a tokenizer's flat metrics, readable without torch (the report reads them)."""

from collections.abc import Mapping

TASK_ERROR_METRICS = ("rmse/", "rmse_percent_range/", "max_error/")
"""The metrics also reported per task when a tokenizer is measured on several tasks."""


def task_errors(metrics: Mapping[str, float]) -> dict[str, dict[str, float]]:
    """Task -> its own error metrics (keys as the pooled ones), from the ``task/<task>/...`` keys of `metrics`."""
    errors: dict[str, dict[str, float]] = {}
    for key, value in metrics.items():
        if key.startswith("task/"):
            task, metric = key.removeprefix("task/").split("/", 1)
            errors.setdefault(task, {})[metric] = value
    return errors
