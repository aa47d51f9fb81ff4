"""The tokenizer studies: every tokenizer kind against carp_msvq, and a tokenizer reused on tasks it never saw.

``tokenizers``: one point per kind of ``study.tokenizer_kinds`` (``-S tokenizer.kind=<kind>``, each kind at the rate
its own ``tokenizer_<kind>`` section sets), every family of the workspace's ``policies`` that can predict the kind's
tokens trained at that point and compared with the same family at carp_msvq. A family that declares the kinds it
takes (next_token: all; carp: carp_msvq) is trained at those points only; a family that takes no tokens at all
(diffusion and the like) does not change with the kind and is trained once, at carp_msvq, as context.

``tokenizer_reuse``: one experiment trains a tokenizer on the source tasks and registers it under `REUSE_ALIAS`
(``dvc exp run register_tokenizer``, no policy trained); then the target tasks run twice, with their own tokenizer
(``tokenizer.source=pipeline``) and with the registered one (``tokenizer.source=models:/<name>@<alias>``). Both arms
are points of one `SettingStudy`, so they resume, replay and compare as the other studies' points do, and the verdict
of "reused" against "own" is the equivalence test of the comparison rules.
"""

import json
import os
import shutil
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from carp.outputs import write_text
from carp.studies.data_efficiency import COMPLETE_MARKER
from carp.studies.point_replay import TOKENIZER_FOLDER
from carp.studies.setting_study import TOKENIZER_METRICS, SettingStudy

REFERENCE_KIND = "carp_msvq"
REUSE_ALIAS = "study-reuse-source"
"""Alias of the source tokenizer's registered version; the target arms' own tokenizers keep the workspace's alias."""
SOURCE_FOLDER = "source"
TOKENIZER_REF_FILE = "tokenizer_ref.json"

KINDS_NOTE = (
    "Bits per chunk are tokens x log2 of the vocabulary (carp_msvq's from its fixed layout); the entropy is that of "
    "the tokens actually used on the held-out windows; repaired chunks are the share of predicted chunks whose tokens "
    "the tokenizer had to repair before decoding them; parameters are the policy's trained ones (the next-token "
    "network is widened over another kind to its size over carp_msvq, next_token.match_size). Each kind runs at the "
    "rate its tokenizer_<kind> section sets."
)


def tokenizer_study(
    kinds: Sequence[str],
    lists: Mapping[str, Sequence[str]],
    takes: Callable[[str, str], bool],
    reference: str = REFERENCE_KIND,
) -> SettingStudy:
    """The tokenizer-kind study over `kinds`, each point training the workspace's families that take its kind.

    Args:
        kinds: the points, tokenizer kinds; `reference` among them.
        lists: the workspace's ``policies``, ``register`` and ``multitask``; a point narrows ``policies`` to the
            families that take its kind, ``register`` to those, and ``multitask`` to the families that take it.
        takes: whether a family can be trained over a kind's tokens.
        reference: the kind every other kind is compared with.

    Raises:
        ValueError: a kind no family of ``policies`` takes (the point would train nothing to compare).
    """
    families, overrides = [], []
    policies = list(lists.get("policies", ()))
    for kind in kinds:
        kept = [family for family in policies if takes(family, kind)]
        if not kept:
            raise ValueError(
                f"tokenizer kind {kind}: no family of policies={policies} is trained over its tokens (next_token "
                "takes every kind)"
            )
        if kept == policies:
            continue
        families.append((kind, tuple(kept)))
        narrowed = [f"policies={_list(kept)}"]
        register = [family for family in lists.get("register", ()) if family in kept]
        multitask = [family for family in lists.get("multitask", ()) if takes(family, kind)]
        for key, remaining in (("register", register), ("multitask", multitask)):
            if remaining != list(lists.get(key, ())):
                narrowed.append(f"{key}={_list(remaining)}")
        overrides.append((kind, tuple(narrowed)))
    return SettingStudy(
        "tokenizers",
        "tokenizer.kind",
        tuple(kinds),
        reference,
        point_families=tuple(families),
        point_overrides=tuple(overrides),
        note=KINDS_NOTE,
    )


def family_takes_kind(kinds_of: Callable[[str], tuple[str, ...] | None]) -> Callable[[str, str], bool]:
    """`takes` for `tokenizer_study` from each family's declared kinds; a family that declares none takes carp_msvq."""
    return lambda family, kind: kind in (kinds_of(family) or (REFERENCE_KIND,))


def source_overrides(source_tasks: Sequence[str]) -> list[str]:
    """The ``-S`` values of the source experiment: its tasks train the tokenizer, registered under `REUSE_ALIAS`."""
    tasks = _list(source_tasks)
    return [f"tasks={tasks}", f"tokenizer.tasks={tasks}", "tokenizer.source=pipeline",
            f"tokenizer.registry_alias={REUSE_ALIAS}"]  # fmt: skip


def source_marker(source_tasks: Sequence[str]) -> dict[str, Any]:
    """What a finished source folder was made for: its tasks and the alias it registered."""
    return {"source_tasks": list(source_tasks), "alias": REUSE_ALIAS}


def run_source(
    source_tasks: Sequence[str],
    output_dir: Path,
    run_experiment: Callable[[str, list[str]], None],
    tokenizer_metrics: Path,
    tokenizer_dir: Path,
    tokenizer_ref: Path,
) -> bool:
    """Train and register the source tokenizer as one experiment unless ``<output_dir>/source`` holds it; True if run.

    The experiment's tokenizer metrics, tokenizer and registry reference are copied into ``source/``, which is
    renamed into place complete, so an interrupted study trains the source again only when it had not finished.

    Raises:
        FileNotFoundError: the experiment left no tokenizer metrics or registry reference.
    """
    folder = Path(output_dir) / SOURCE_FOLDER
    marker = source_marker(source_tasks)
    if (folder / COMPLETE_MARKER).is_file() and json.loads((folder / COMPLETE_MARKER).read_text()) == marker:
        return False
    run_experiment(f"tokenizer_reuse-{SOURCE_FOLDER}", source_overrides(source_tasks))
    staging = folder.with_name(f".{folder.name}.tmp")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    for source, name in ((tokenizer_metrics, TOKENIZER_METRICS), (tokenizer_ref, TOKENIZER_REF_FILE)):
        if not Path(source).is_file():
            raise FileNotFoundError(f"{source}: the source tokenizer's experiment left nothing here")
        shutil.copyfile(source, staging / name)
    if Path(tokenizer_dir).is_dir():
        shutil.copytree(tokenizer_dir, staging / TOKENIZER_FOLDER)
    write_text(staging / COMPLETE_MARKER, json.dumps(marker, indent=2) + "\n")
    shutil.rmtree(folder, ignore_errors=True)
    os.replace(staging, folder)
    return True


def reuse_study(
    target_tasks: Sequence[str], source_tasks: Sequence[str], source_uri: str, source_metrics: Mapping[str, float]
) -> SettingStudy:
    """The reuse study's two arms on `target_tasks`: their own tokenizer (reference) and the source one (`source_uri`).

    `source_metrics` (the source tokenizer's own held-out figures) go into the report's note.
    """
    tasks = _list(target_tasks)
    error = source_metrics.get("rmse_percent_range/mean")
    on_source = "" if error is None else f", {error:.2f}% of range RMSE on their held-out windows"
    note = (
        f"The own arm trains a tokenizer on {', '.join(target_tasks)} (each task normalized with its own statistics); "
        f"the reused arm takes {source_uri}, trained on {', '.join(source_tasks)}{on_source}, and never fitted to "
        "these tasks. Reuse holds on a task for a family when the reused arm is on par with the own arm within the "
        "comparison margin; a difference either way, or too few seeds, says it does not or is not decided."
    )
    return SettingStudy(
        "tokenizer_reuse",
        "tokenizer.source",
        ("pipeline", source_uri),
        "pipeline",
        shared_overrides=(f"tasks={tasks}", f"tokenizer.tasks={tasks}"),
        note=note,
    )


def reuse_marker(layout_marker: Mapping[str, Any], target_tasks: Sequence[str], source_tasks: Sequence[str]):
    """The arms' layout: the target tasks, the workspace's families and seeds, and the source it reuses."""
    return {**layout_marker, "tasks": list(target_tasks), "source_tasks": list(source_tasks)}


def _list(names: Sequence[str]) -> str:
    return "[" + ",".join(names) + "]"
