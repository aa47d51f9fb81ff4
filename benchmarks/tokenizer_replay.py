"""Success of scripted demos replayed open loop through tokenizers' round trips (`carp.evaluation.replay`).

Every executed chunk of a demo is tokenized and decoded before the env runs it; the first row replays the recorded
actions unchanged (the simulation's own reproducibility). Run it in a pipeline directory after `dvc repro
train_tokenizer`; compare tokenizers trained elsewhere, or saved tokenizers of any kind (`carp.tokenizer.kinds`), by
passing their directories. The task's statistics
come from its ingested data and To, Ta, H from params.yaml, as a policy's do.

    .venv/bin/python benchmarks/tokenizer_replay.py --task square [--tokenizers models/tokenizer other/models/tokenizer]
        [--demos 50] [--workers 2] [--params params.yaml]
"""

import argparse
import os
from pathlib import Path

from carp.config import load_params
from carp.data.ingest import NORMALIZATION_FILENAME
from carp.data.normalizer import load_normalizers
from carp.evaluation.replay import replay_demonstrations
from carp.tokenizer.kinds.registry import load_tokenizer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", required=True, help="lift, can or square: reads data/raw/<task>.hdf5")
    parser.add_argument("--tokenizers", nargs="*", type=Path, default=[Path("models/tokenizer")])
    parser.add_argument("--demos", type=int, default=50, help="the first this many demos of the file")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--params", type=Path, default=Path("params.yaml"))
    arguments = parser.parse_args()
    data = load_params(arguments.params).data
    raw_path = Path("data/raw") / f"{arguments.task}.hdf5"
    normalizer = load_normalizers(Path("data/processed") / arguments.task / NORMALIZATION_FILENAME)["action"]

    rows = []
    for tokenizer in [None, *arguments.tokenizers]:
        results = replay_demonstrations(
            raw_path,
            normalizer,
            None if tokenizer is None else load_tokenizer(tokenizer),
            data.obs_steps,
            data.action_steps,
            data.action_horizon,
            num_demos=arguments.demos,
            workers=arguments.workers,
        )
        successes = sum(result.success for result in results)
        rows.append(("recorded actions" if tokenizer is None else str(tokenizer), successes, len(results)))
    settings = f"To={data.obs_steps}, Ta={data.action_steps}, H={data.action_horizon}"
    print(f"open-loop replay of {arguments.task} demos, {settings}")
    width = max(len(row[0]) for row in rows) + 2
    print(f"{'chunks through':<{width}}{'success':>10}{'rate':>8}")
    for name, successes, total in rows:
        print(f"{name:<{width}}{f'{successes}/{total}':>10}{100 * successes / total:>7.0f}%")


if __name__ == "__main__":
    main()
