"""Open-loop replay through a study point's own tokenizer: what each setting's rate buys, in task success.

A finished point of the scales or codebook study keeps a copy of its tokenizer (``<point>/tokenizer``). `replay_point`
replays the first demos of every task through that tokenizer's round trip (`carp.evaluation.replay`: each executed
chunk tokenized and decoded before the simulator runs it) and writes ``<point>/replay.json``, task -> successes and
demos, once; the study's report reads it beside the policy's success. A point without a tokenizer copy (harvested by
hand, or with replay turned off) simply has no replay figures.
"""

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from carp.data.ingest import NORMALIZATION_FILENAME
from carp.data.normalizer import load_normalizers
from carp.data.robomimic_io import DatasetError
from carp.evaluation.replay import replay_demonstrations
from carp.outputs import write_text
from carp.tokenizer.kinds.registry import load_tokenizer

REPLAY_FILE = "replay.json"
TOKENIZER_FOLDER = "tokenizer"


@dataclass(frozen=True)
class ReplaySetup:
    """Where a workspace keeps the demos and statistics a replay needs, and how many demos to replay.

    Attributes:
        raw_dir: the demo files, ``<raw_dir>/<task>.hdf5`` (collected by carp: each demo carries its seed).
        processed_dir: the ingested data, ``<processed_dir>/<task>/normalization.json`` (the action statistics).
        obs_steps: ``To``.
        action_steps: ``Ta``, rows executed per chunk.
        horizon: ``H``, rows per chunk.
        num_demos: the first this many demos of each task's file; 0 replays none.
        workers: simulator processes.
    """

    raw_dir: Path
    processed_dir: Path
    obs_steps: int
    action_steps: int
    horizon: int
    num_demos: int
    workers: int = 1


def replay_point(point_dir: Path, tasks: Sequence[str], setup: ReplaySetup) -> dict[str, dict[str, int]]:
    """The point's replay figures, task -> {"successes", "demos"}; measured and written when not yet on disk.

    Nothing is measured without a tokenizer copy or with ``setup.num_demos`` 0 (the result is then empty), and a task
    whose demos carry no collection seed (a file carp did not collect) is left out.
    """
    point_dir = Path(point_dir)
    stored = read_replay(point_dir)
    tokenizer_dir = point_dir / TOKENIZER_FOLDER
    if stored or setup.num_demos == 0 or not tokenizer_dir.is_dir():
        return stored
    tokenizer = load_tokenizer(tokenizer_dir)
    figures = {}
    for task in tasks:
        normalizer = load_normalizers(Path(setup.processed_dir) / task / NORMALIZATION_FILENAME)["action"]
        try:
            results = replay_demonstrations(
                Path(setup.raw_dir) / f"{task}.hdf5",
                normalizer,
                tokenizer,
                setup.obs_steps,
                setup.action_steps,
                setup.horizon,
                num_demos=setup.num_demos,
                workers=setup.workers,
            )
        except DatasetError:
            continue  # not replayable: the demos do not say which seed reproduces them
        figures[task] = {"successes": sum(bool(result.success) for result in results), "demos": len(results)}
    write_text(point_dir / REPLAY_FILE, json.dumps(figures, indent=2) + "\n")
    return figures


def read_replay(point_dir: Path) -> dict[str, dict[str, int]]:
    """The point's stored replay figures; empty when it has none."""
    path = Path(point_dir) / REPLAY_FILE
    return json.loads(path.read_text()) if path.is_file() else {}


def replay_cell(figures: Mapping[str, Mapping[str, int]], task: str) -> str:
    """``successes/demos`` of `task`, or ``-`` when the point has no replay of it."""
    entry = figures.get(task)
    return f"{entry['successes']}/{entry['demos']}" if entry else "-"


def nominal_rate(tokenizer_dir: Path) -> dict[str, float]:
    """``bits_per_chunk`` (tokens x log2 V) and ``tokens_per_chunk/mean`` of a point's tokenizer copy.

    carp_msvq's metrics file holds its errors and code usage only; its rate follows from its fixed layout. Empty
    without a tokenizer copy; a kind's measured rate in its metrics file takes precedence.
    """
    if not Path(tokenizer_dir).is_dir():
        return {}
    tokenizer = load_tokenizer(tokenizer_dir)
    tokens = float(tokenizer.tokens_per_chunk.mean)
    return {"bits_per_chunk": tokens * float(np.log2(tokenizer.vocabulary_size)), "tokens_per_chunk/mean": tokens}
