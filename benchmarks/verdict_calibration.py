"""How often the report's verdicts are wrong, and how often its intervals cover, on simulated families with known truth.

Each row is a regime of `carp.reporting.calibration` (true family rates, training seeds, episodes per seed, the sd of
seed rates, the share of episodes following a state's shared difficulty and a family's own difficulty of that state,
and whether seeds share their initial states), simulated `--runs` times. Columns: the share of runs with a false
"better", with any wrong verdict (the family-wise error), with a false "on par", the coverage of the family-rate,
family-difference and per-network intervals, and the share of pairs given a family verdict; each share with its
Monte-Carlo standard error.

    .venv/bin/python benchmarks/verdict_calibration.py [--runs 1000] [--alpha 0.05] [--margin 0.05] [--out table.md]
"""

import argparse
from pathlib import Path

import pandas as pd
from tqdm.auto import tqdm

from carp.reporting.calibration import CellResult, Regime, default_regimes, run_cell


def cell_row(regime: Regime, cell: CellResult) -> dict[str, str]:
    """One table row: the regime, then each share with its Monte-Carlo standard error, in percent."""

    def share(name: str) -> str:
        value, error = cell.share(name)
        return "-" if value != value else f"{100 * value:.1f} ({100 * error:.1f})"

    equal = len(set(regime.rates)) == 1
    return {
        "families": f"{len(regime.rates)} x {regime.rates[0]:g}" if equal else "/".join(map(str, regime.rates)),
        "seeds": str(regime.seeds),
        "episodes": str(regime.episodes),
        "seed sd": f"{100 * regime.seed_spread:g}",
        "state / family-state": f"{regime.state_share:g} / {regime.family_state_share:g}",
        "states": "shared" if regime.shared_states else "distinct",
        "false better": share("false_better"),
        "any wrong verdict": share("any_verdict_error"),
        "false on par": share("false_on_par"),
        "rate covered": share("rate"),
        "difference covered": share("difference"),
        "network covered": share("network"),
        "pairs decided": f"{100 * cell.family_verdicts / cell.pairs:.1f}",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=1000, help="simulated runs per regime")
    parser.add_argument("--alpha", type=float, default=0.05)
    parser.add_argument("--margin", type=float, default=0.05)
    parser.add_argument("--min-seeds", type=int, default=3)
    parser.add_argument("--regimes", type=int, default=None, help="only the first this many regimes (a quick look)")
    parser.add_argument("--out", type=Path, default=None, help="also write the table here as Markdown")
    arguments = parser.parse_args()
    regimes = default_regimes()[: arguments.regimes]
    rows = []
    for regime in tqdm(regimes, desc="regimes", unit="regime"):
        cell = run_cell(
            regime, arguments.runs, margin=arguments.margin, alpha=arguments.alpha, min_seeds=arguments.min_seeds
        )
        rows.append(cell_row(regime, cell))
    table = pd.DataFrame(rows).to_markdown(index=False)
    print(
        f"{arguments.runs} runs per regime, alpha {arguments.alpha}, margin {arguments.margin}, "
        f"min_seeds {arguments.min_seeds}; Monte-Carlo standard errors in parentheses"
    )
    print(table)
    if arguments.out is not None:
        arguments.out.write_text(table + "\n")


if __name__ == "__main__":
    main()
