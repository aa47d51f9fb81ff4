"""The CARP paper's claims a run can check: success (from the decided pairs), precision and speed.

A success claim reads the pair's family verdict; a precision claim is a Welch test over training seeds that joins the
report's one correction (`carp.reporting.comparison.decide_report`); a speed claim is the latency ratio's interval.
"""

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from carp.reporting import statistics, verdicts
from carp.reporting.runs import Runs, measure_columns, pooled_measure

PAPER_CLAIMS = (
    ("CARP's success is on par with DP-C", "carp", "diffusion_unet", "on par"),
    ("CARP's success is better than next-token's", "carp", "next_token", "better"),
)
"""(claim, family, rival, what the paper says of the pair) for the success claims a run can check."""


PRECISION_CLAIMS = (
    ("CARP's insertion precision is comparable to DP-C's", "carp", "diffusion_unet", "insertion_offset_mm"),
)
"""(claim, family, rival, per-episode measure) for the precision claims (CARP's Tables 4-5): lower is more precise."""


SPEED_CLAIMS = (
    ("CARP is about 10x faster per chunk than DP-C", "carp", "diffusion_unet"),
    ("CARP is faster per chunk than DP-T", "carp", "diffusion_transformer"),
)
"""(claim, family, slower rival) for the inference-speed claims: the rival's latency over the family's."""


def latency_ratio(slower: Runs, faster: Runs, level: float = 0.95, resamples: int = 4000, seed: int = 0):
    """How many times longer a chunk takes `slower` than `faster`, with a percentile bootstrap interval.

    The ratio of the median per-episode chunk latencies, resampled over episodes; None when an episode table lacks
    latencies.
    """
    samples = []
    for runs in (slower, faster):
        frames = [run.episodes for run in runs.values()]
        if not all("chunk_ms_median" in frame for frame in frames):
            return None
        values = np.concatenate([frame["chunk_ms_median"].to_numpy(dtype=float) for frame in frames])
        samples.append(values[np.isfinite(values)])
    if not all(len(values) for values in samples):
        return None
    generator = np.random.default_rng(seed)
    medians = [
        np.median(values[generator.integers(0, len(values), size=(resamples, len(values)))], axis=1)
        for values in samples
    ]
    ratios = medians[0] / medians[1]
    tail = 100 * (1 - level) / 2
    return statistics.Interval(
        float(np.median(samples[0]) / np.median(samples[1])),
        float(np.percentile(ratios, tail)),
        float(np.percentile(ratios, 100 - tail)),
    )


@dataclass(frozen=True)
class PrecisionTest:
    """One precision claim on one task: Welch's test of two families' per-seed mean measures (lower is more precise).

    Attributes:
        task, claim, family, rival, column: the claim (`PRECISION_CLAIMS`) and the task it is tested on.
        seed_means: (n_family,), (n_rival,) each training seed's mean of the measure over its measured episodes.
        networks: the pooled episode figures, stated as the networks' (they do not decide the claim).
        min_seeds: training seeds per family the test needs.
        p_value: Welch's p over training seeds; None with fewer than `min_seeds` seeds in either family.
        difference: family's mean minus rival's, over seeds (NaN without a p-value).
        interval: its 95% Welch interval, uncorrected (NaN without a p-value).
        adjusted_p_value: p after the report's correction (`decide_report`); None until then.
    """

    task: str
    claim: str
    family: str
    rival: str
    column: str
    seed_means: tuple[np.ndarray, np.ndarray]
    networks: str
    min_seeds: int
    p_value: float | None
    difference: float
    interval: tuple[float, float]
    adjusted_p_value: float | None = None


def precision_tests(
    evaluations: Mapping[str, Mapping[str, Runs]], min_seeds: int = verdicts.DEFAULT_MIN_SEEDS
) -> list[PrecisionTest]:
    """The precision claims a run can test, per task: families it trained with a measure its task takes."""
    tests = []
    for task, task_runs in evaluations.items():
        for claim, family, rival, column in PRECISION_CLAIMS:
            if family not in task_runs or rival not in task_runs or column not in measure_columns(task_runs):
                continue
            pooled = [pooled_measure(task_runs[name], column) for name in (family, rival)]
            pooled = [values[np.isfinite(values)] for values in pooled]
            if not all(values.size for values in pooled):
                continue
            networks = (
                f"{column} over the networks' measured episodes: {family} mean {pooled[0].mean():.2f} "
                f"({pooled[0].size} episodes), {rival} mean {pooled[1].mean():.2f} ({pooled[1].size} episodes)"
            )
            seed_means = (_seed_means(task_runs[family], column), _seed_means(task_runs[rival], column))
            p_value, difference, interval = None, float("nan"), (float("nan"), float("nan"))
            if min(means.size for means in seed_means) >= min_seeds:
                result = stats.ttest_ind(seed_means[0], seed_means[1], equal_var=False)
                low, high = result.confidence_interval(0.95)
                p_value = float(result.pvalue)
                difference = float(seed_means[0].mean() - seed_means[1].mean())
                interval = (float(low), float(high))
            tests.append(
                PrecisionTest(
                    task, claim, family, rival, column, seed_means, networks, min_seeds, p_value, difference, interval
                )
            )
    return tests


def claims_table(
    evaluations: Mapping[str, Mapping[str, Runs]],
    comparisons: Mapping[str, Sequence["verdicts.PairComparison"]],
    precision: Sequence[PrecisionTest] = (),
    alpha: float = 0.05,
    suffix: str = "",
) -> pd.DataFrame:
    """The paper's claims that this run can check, per task: the verdict and the numbers behind it.

    A success claim holds when the pair's family verdict says what the paper says ("on par" also holds when CARP comes
    out better), and is "not decided (n training seeds)" when the pair has too few seeds for a family verdict; a speed
    claim states the latency ratio with its interval and holds when the interval lies above 1; a precision claim
    holds when CARP's per-seed mean offset is lower and its test's p, corrected with the report's verdicts, is below
    `alpha`. Claims about families the run did not train, or measures its task lacks, are left out.

    Args:
        evaluations: task -> family -> runs.
        comparisons: task -> the pairs compared, each policy named by its family and `suffix`.
        precision: the precision tests of these evaluations, corrected (`decide_report`).
        alpha: family-wise significance level the verdicts were corrected at.
        suffix: appended to a family's name in `comparisons` (`carp.outputs.MULTITASK_SUFFIX` for the multi-task
            policies' claims).
    """
    rows = []
    for task, task_runs in evaluations.items():
        pairs = comparisons.get(task, ())
        rows += [{"task": task, **row} for row in _success_claims(pairs, suffix)]
        rows += [{"task": task, **_precision_claim(test, alpha)} for test in precision if test.task == task]
        rows += [{"task": task, **row} for row in _speed_claims(task_runs)]
    return pd.DataFrame(rows, columns=["task", "claim", "verdict", "evidence"])


def _success_claims(pairs: Sequence["verdicts.PairComparison"], suffix: str) -> list[dict[str, str]]:
    rows = []
    for claim, family, rival, paper in PAPER_CLAIMS:
        comparison = find_pair(pairs, family + suffix, rival + suffix)
        if comparison is None:
            continue
        verdict = oriented_verdict(comparison, family + suffix, rival + suffix)
        holds = verdict in ("on par", "better") if paper == "on par" else verdict == "better"
        status = "holds" if holds else (comparison.verdict if verdict == "not decided" else "does not hold")
        rows.append({"claim": claim, "verdict": status, "evidence": comparison.explanation})
    return rows


def _precision_claim(test: PrecisionTest, alpha: float) -> dict[str, str]:
    """A precision test's row: not decided below its seed count, else by its corrected p and the sign."""
    if test.p_value is None:
        seeds = min(means.size for means in test.seed_means)
        return {
            "claim": test.claim,
            "verdict": f"not decided ({seeds} training seed{'s' if seeds != 1 else ''})",
            "evidence": f"{test.networks}; a family verdict needs {test.min_seeds} training seeds with measured "
            "episodes each",
        }
    if test.adjusted_p_value is None:
        raise ValueError(f"the precision test of {test.claim!r} on {test.task} was not corrected (decide_report)")
    if test.adjusted_p_value >= alpha:
        verdict, finding = "not decided", "no difference in the families' means detected"
    else:
        better = test.difference < 0
        verdict = "holds" if better else "does not hold"
        finding = f"{test.family} {'more' if better else 'less'} precise"
    low, high = test.interval
    evidence = (
        f"per-seed mean {test.column}: {test.family} {_listed(test.seed_means[0])}, {test.rival} "
        f"{_listed(test.seed_means[1])}; {finding} (Welch over training seeds p = {test.p_value:.3g}, corrected "
        f"{test.adjusted_p_value:.3g}; difference {test.difference:+.2f}, 95% interval {low:+.2f} to {high:+.2f}); "
        f"{test.networks}"
    )
    return {"claim": test.claim, "verdict": verdict, "evidence": evidence}


def _seed_means(runs: Runs, column: str) -> np.ndarray:
    """(k,) each training seed's mean of a per-episode measure over the episodes that took it; seeds with none out."""
    means = []
    for _, run in sorted(runs.items()):
        if column in run.episodes:
            values = run.episodes[column].to_numpy(dtype=float)
            values = values[np.isfinite(values)]
            if values.size:
                means.append(values.mean())
    return np.array(means)


def _listed(values: np.ndarray) -> str:
    return ", ".join(f"{value:.2f}" for value in values)


def _speed_claims(task_runs: Mapping[str, Runs]) -> list[dict[str, str]]:
    rows = []
    for claim, family, rival in SPEED_CLAIMS:
        if family not in task_runs or rival not in task_runs:
            continue
        ratio = latency_ratio(task_runs[rival], task_runs[family])
        if ratio is None:
            continue
        evidence = (
            f"{rival} takes {ratio.estimate:.1f}x as long per chunk as {family} at batch 1 (95% bootstrap interval "
            f"{ratio.low:.1f}-{ratio.high:.1f}x over episodes' median latencies)"
        )
        rows.append({"claim": claim, "verdict": "holds" if ratio.low > 1 else "does not hold", "evidence": evidence})
    return rows


def find_pair(comparisons: Sequence["verdicts.PairComparison"], family: str, rival: str):
    """The comparison of `family` and `rival` in either order, or None when the run did not pair them."""
    for comparison in comparisons:
        if {comparison.first, comparison.second} == {family, rival}:
            return comparison
    return None


def oriented_verdict(comparison: "verdicts.PairComparison", family: str, rival: str) -> str:
    """The pair's verdict from `family`'s side: "better", "worse", "on par" or "not decided"."""
    verdict = comparison.verdict
    if verdict.startswith("on par"):
        return "on par"
    if verdict == f"{family} better":
        return "better"
    if verdict == f"{rival} better":
        return "worse"
    return "not decided"
