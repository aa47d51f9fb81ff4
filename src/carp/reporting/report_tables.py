"""The report's per-task tables and figures: success, latency, the inference budget, the tokenizer, the sweep.

Each table is strings, ready to print; each figure is written to a path and the path returned.
"""

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

from carp.evaluation.metrics import wilson_interval  # noqa: E402
from carp.reporting.figures import finish_figure  # noqa: E402
from carp.tokenizer.task_metrics import task_errors  # noqa: E402

CONTROL_STEPS = 400
"""Control steps of the Table-1-style inference budget for a task carp does not know (the paper's supplementary
table 1: 400 steps, the arm tasks' episode limit)."""


def budget_steps(task: str) -> int:
    """Control steps of `task`'s inference budget: its protocol's episode limit (arms 400, Push-T 300)."""
    from carp.tasks import TASK_NAMES, get_task

    return get_task(task).default_max_steps if task in TASK_NAMES else CONTROL_STEPS


def comparison_table(
    evaluations: Mapping[str, Mapping], histories: Mapping[str, pd.DataFrame] | None = None
) -> pd.DataFrame:
    """One task's row per policy family: success with its 95% Wilson interval, latency, model calls, size, backend.

    Args:
        evaluations: policy family -> that family's evaluation metrics on the task.
        histories: policy family -> its training history; the ``epoch_seconds`` sum is the training wall time.
    """
    rows = []
    for policy, metrics in evaluations.items():
        successes, episodes = int(metrics["successes"]), int(metrics["episodes"])
        lower, upper = wilson_interval(successes, episodes)
        history = (histories or {}).get(policy)
        seconds = float(history["epoch_seconds"].sum()) if history is not None and "epoch_seconds" in history else None
        rows.append(
            {
                "policy": policy,
                "inference": metrics.get("inference") or token_choice(metrics.get("top_k")),
                "success": f"{successes}/{episodes}",
                "rate": f"{100 * successes / episodes:.1f}%",
                "95% interval": f"{100 * lower:.1f}-{100 * upper:.1f}%",
                "crashed": int(metrics.get("crashed_episodes", 0)),
                "predict ms (median / p90)": _pair(metrics, "latency_predict_ms"),
                "decode ms (median / p90)": _pair(metrics, "latency_decode_ms"),
                "model calls": _integer(metrics.get("model_calls_per_chunk")),
                "parameters": _integer(metrics.get("num_parameters")),
                "training": "-" if seconds is None else f"{seconds / 60:.1f} min",
                "backend": metrics.get("backend", "-"),
            }
        )
    return pd.DataFrame(rows)


def success_table(evaluation: Mapping[str, Mapping[str, Mapping]]) -> pd.DataFrame:
    """One row per (task, policy): successes, rate, 95% Wilson interval, mean episode length, inference setting.

    A run with a policy that reports repaired chunks (the next-token family over a kind such as FAST) adds the
    column `repaired chunks`: the share of predicted chunks whose tokens the tokenizer repaired, "-" for the others.
    """
    repairs = any("repaired_chunk_rate" in metrics for policies in evaluation.values() for metrics in policies.values())
    rows = []
    for task, policies in evaluation.items():
        for policy, metrics in policies.items():
            successes, episodes = int(metrics["successes"]), int(metrics["episodes"])
            lower, upper = wilson_interval(successes, episodes)
            rows.append(
                {
                    "task": task,
                    "policy": policy,
                    "success": f"{successes}/{episodes}",
                    "rate": f"{100 * successes / episodes:.1f}%",
                    "95% interval": f"{100 * lower:.1f}-{100 * upper:.1f}%",
                    "mean steps": f"{metrics.get('mean_episode_steps', float('nan')):.0f}",
                    "crashed": int(metrics.get("crashed_episodes", 0)),
                    "decoding": metrics.get("inference") or token_choice(metrics.get("top_k")),
                }
            )
            if repairs:
                rate = metrics.get("repaired_chunk_rate")
                rows[-1]["repaired chunks"] = "-" if rate is None else f"{100 * rate:.1f}%"
    return pd.DataFrame(rows)


def multitask_table(
    multitask: Mapping[str, Mapping[str, Mapping]], evaluation: Mapping[str, Mapping[str, Mapping]]
) -> pd.DataFrame:
    """One row per (task, family) of a multi-task policy: its success and that of the family's single-task policy.

    Each success is given as successes/episodes and rate with its 95% Wilson interval; "-" where the run has no
    single-task policy of that family on the task.

    Args:
        multitask: task -> family -> the multi-task policy's evaluation metrics on the task.
        evaluation: task -> family -> the single-task policies' evaluation metrics.
    """
    rows = []
    for task, families in multitask.items():
        for policy, metrics in families.items():
            single = evaluation.get(task, {}).get(policy)
            multi_success, multi_interval = _success_and_interval(metrics)
            single_success, single_interval = ("-", "-") if single is None else _success_and_interval(single)
            rows.append(
                {
                    "task": task,
                    "policy": policy,
                    "multi-task success": multi_success,
                    "multi-task 95% interval": multi_interval,
                    "single-task success": single_success,
                    "single-task 95% interval": single_interval,
                }
            )
    return pd.DataFrame(rows)


def _success_and_interval(metrics: Mapping) -> tuple[str, str]:
    successes, episodes = int(metrics["successes"]), int(metrics["episodes"])
    lower, upper = wilson_interval(successes, episodes)
    return f"{successes}/{episodes} ({100 * successes / episodes:.1f}%)", f"{100 * lower:.1f}-{100 * upper:.1f}%"


def token_choice(top_k: float | None) -> str:
    """How an evaluation chose tokens: "greedy", "top-<k> draws", or "-" for metrics that predate the record."""
    if top_k is None:
        return "-"
    return "greedy" if int(top_k) == 1 else f"top-{int(top_k)} draws"


def latency_table(evaluation: Mapping[str, Mapping[str, Mapping]]) -> pd.DataFrame:
    """Per (task, policy): per-chunk latency (ms) of prediction and decoding, at batch 1 in rollouts and batched.

    For an image policy, "encoder median" is the camera encoder's share of the prediction ("-" for state policies),
    so the latency without the encoder is the prediction minus it.
    """
    rows = []
    for task, policies in evaluation.items():
        for policy, metrics in policies.items():
            for setting, prefix in (("batch 1 (rollouts)", "latency"), ("batched", "batched_latency")):
                if f"{prefix}_predict_ms_median" not in metrics:
                    continue
                batch = metrics.get("batched_latency_batch_size", "") if prefix == "batched_latency" else 1
                backend = metrics.get("backend", "-") if prefix == "latency" else "torch"
                rows.append(
                    {
                        "task": task,
                        "policy": policy,
                        "setting": f"{setting}" + (f", B={batch}" if prefix == "batched_latency" else ""),
                        "backend": backend,
                        "predict median": f"{metrics[f'{prefix}_predict_ms_median']:.2f}",
                        "predict p90": f"{metrics[f'{prefix}_predict_ms_p90']:.2f}",
                        "decode median": f"{metrics[f'{prefix}_decode_ms_median']:.2f}",
                        "decode p90": f"{metrics[f'{prefix}_decode_ms_p90']:.2f}",
                        "encoder median": _milliseconds(metrics.get(f"{prefix}_encode_ms_median")),
                    }
                )
    return pd.DataFrame(rows)


def _milliseconds(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def inference_budget_lines(evaluation: Mapping[str, Mapping[str, Mapping]]) -> list[str]:
    """Table-1-style lines: per (task, policy), total inference time over the task's episode limit (`budget_steps`).

    A chunk is predicted every ``action_steps`` (Ta) control steps, so N steps take ``ceil(N / Ta)`` chunks at
    the median batch-1 latency of prediction plus decoding (the camera encoder included for image policies). The
    cameras an image policy sees are rendered at every control step; that time is given apart.
    """
    lines = []
    for task, policies in evaluation.items():
        steps = budget_steps(task)
        for policy, metrics in policies.items():
            if "latency_predict_ms_median" not in metrics or "action_steps" not in metrics:
                continue
            chunks = -(-steps // int(metrics["action_steps"]))
            chunk_ms = metrics["latency_predict_ms_median"] + metrics["latency_decode_ms_median"]
            lines.append(
                f"{task}, {policy} ({metrics.get('inference', '-')}, {metrics.get('backend', '-')}): "
                f"{chunks * chunk_ms / 1000:.2f} s of inference over {steps} control steps "
                f"({chunks} chunks of {chunk_ms:.2f} ms)"
                + (
                    f", {metrics['latency_encode_ms_median']:.2f} ms of each in the camera encoder"
                    if "latency_encode_ms_median" in metrics
                    else ""
                )
                + (
                    f"; rendering the cameras: {steps * metrics['render_step_ms_median'] / 1000:.2f} s "
                    f"({metrics['render_step_ms_median']:.2f} ms per step)"
                    if "render_step_ms_median" in metrics
                    else ""
                )
            )
    return lines


def plot_success_against_latency(evaluation: Mapping[str, Mapping[str, Mapping]], path: Path) -> Path:
    """Success rate (with its 95% interval) against batch-1 latency per chunk on a log axis; one point per pair."""
    figure, axis = plt.subplots(figsize=(6, 3.6))
    for task, policies in evaluation.items():
        for policy, metrics in policies.items():
            if "latency_predict_ms_median" not in metrics:
                continue
            successes, episodes = int(metrics["successes"]), int(metrics["episodes"])
            lower, upper = wilson_interval(successes, episodes)
            rate = successes / episodes
            latency = metrics["latency_predict_ms_median"] + metrics["latency_decode_ms_median"]
            axis.errorbar(
                [latency],
                [100 * rate],
                yerr=[[100 * (rate - lower)], [100 * (upper - rate)]],
                fmt="o",
                capsize=3,
                label=f"{task}: {policy}",
            )
    axis.set_xscale("log")
    axis.set_xlabel("latency per chunk at batch 1 (ms, log scale)")
    axis.set_ylabel("success rate (%)")
    axis.set_ylim(0, 105)
    return finish_figure(figure, axis, path)


def _pair(metrics: Mapping, prefix: str) -> str:
    if f"{prefix}_median" not in metrics:
        return "-"
    return f"{metrics[f'{prefix}_median']:.2f} / {metrics[f'{prefix}_p90']:.2f}"


def _integer(value: float | None) -> str:
    return "-" if value is None else f"{int(value):,}"


TOKENIZER_COLUMNS = {
    "rmse": "RMSE",
    "rmse_percent_range": "RMSE % of range",
    "max_error": "max error",
    "usage/all_scales": "code usage",
    "perplexity": "perplexity",
}


def tokenizer_table(metrics: Mapping[str, float]) -> pd.DataFrame:
    """Per-dimension rows from flat tokenizer metrics keyed ``<metric>/<dimension>``."""
    # Aggregates ("mean", "max") are summarized in the text, not listed as dimensions.
    dimensions = [
        key.split("/", 1)[1] for key in metrics if key.startswith("rmse/") and key not in ("rmse/mean", "rmse/max")
    ]
    rows = []
    for dimension in dimensions:
        row = {"dimension": dimension}
        for key, label in TOKENIZER_COLUMNS.items():
            value = metrics.get(f"{key}/{dimension}")
            row[label] = "" if value is None else f"{value:.4g}"
        rows.append(row)
    return pd.DataFrame(rows)


def tokenizer_task_table(metrics: Mapping[str, float]) -> pd.DataFrame:
    """One row per task of a tokenizer measured on several tasks (`carp.tokenizer.task_metrics`); empty otherwise."""
    rows = []
    for task, own in task_errors(metrics).items():
        dimensions = [key.split("/", 1)[1] for key in own if key.startswith("rmse_percent_range/")]
        worst = max(
            (name for name in dimensions if name not in ("mean", "max")),
            key=lambda name: own[f"rmse_percent_range/{name}"],
        )
        rows.append(
            {
                "task": task,
                "RMSE % of range (mean)": f"{own['rmse_percent_range/mean']:.3g}",
                "worst dimension": f"{worst} ({own[f'rmse_percent_range/{worst}']:.3g}%)",
                "max error": f"{own['max_error/max']:.4g}",
            }
        )
    return pd.DataFrame(rows)


def plot_curves(history: pd.DataFrame, columns: Sequence[str], title: str, path: Path, log_scale: bool = True) -> Path:
    """Plot per-epoch columns of a history table to a PNG."""
    figure, axis = plt.subplots(figsize=(6, 3.2))
    for column in columns:
        if column in history:
            axis.plot(history["epoch"], history[column], label=column)
    axis.set_xlabel("epoch")
    axis.set_title(title)
    if log_scale and (history[[c for c in columns if c in history]] > 0).all().all():
        axis.set_yscale("log")
    return finish_figure(figure, axis, path)


def plot_sweep(trials: pd.DataFrame, path: Path) -> Path:
    """Validation success against the number of scales K, one line per codebook size (the paper's ablation on K)."""
    figure, axis = plt.subplots(figsize=(5, 3.2))
    for size, group in trials.groupby("codebook_size"):
        ordered = group.sort_values("num_scales")
        axis.plot(ordered["num_scales"], 100 * ordered["validation_success_rate"], marker="o", label=f"V={size}")
    axis.set_xlabel("number of scales K")
    axis.set_ylabel("validation success rate (%)")
    axis.set_ylim(0, 105)
    return finish_figure(figure, axis, path)
