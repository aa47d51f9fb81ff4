"""Run one of the paper's studies as DVC experiments in this workspace (`make study STUDY=<name>`).

data_efficiency: one experiment per size of `study.data_efficiency_sizes` (`dvc exp run -n data-efficiency-<N> -S
data.num_demos=<largest> -S data.subset_size=<N>`), each size's evaluations copied into
reports/studies/data_efficiency/size<N>/, then reports/studies/data_efficiency/report.md and report.html. Run it again
after an interruption: finished sizes are not run again. params.yaml is put back as it was when the study ends.
The report adds the families of the study folders in `study.references` (the same study run in other clones).

scales, codebook: one experiment per point of `study.scale_schedules` (`dvc exp run -n scales-K<k> -S scales=[...]`)
or `study.codebook_sizes` (`-n codebook-V<v> -S codebook_size=<v>`), each point's evaluations and tokenizer metrics
copied into reports/studies/<study>/<point>/ with the point's tokenizer, the first `study.replay_demos` demos of each
task replayed open loop through that tokenizer, each point compared with the workspace's own setting. Finished points
are not run again; `--report-only` writes the report from the points that exist (this folder's and the references').

tokenizers: one experiment per kind of `study.tokenizer_kinds` (`-n tokenizers-<kind> -S tokenizer.kind=<kind>`), each
training the families of `policies` that take the kind (`policies`, `register` and `multitask` narrowed with `-S`
where some do not), harvested, replayed and compared with carp_msvq as the scales and codebook points are.

tokenizer_reuse: one experiment (`-n tokenizer_reuse-source ... register_tokenizer`) trains a tokenizer on
`study.reuse_source_tasks` and registers it under the alias `study-reuse-source`, kept in
reports/studies/tokenizer_reuse/source/; then `study.reuse_target_tasks` run as two points, `own`
(`tokenizer.source=pipeline`) and `reused` (`tokenizer.source=models:/<name>@study-reuse-source`), each compared
with the other on every task and family.
"""

import argparse
import json
import os
import subprocess
import sys

from stage_support import (
    EVAL_REPORT_DIR,
    PROCESSED_DIR,
    PROJECT_DIR,
    RAW_DIR,
    REPORTS_DIR,
    TOKENIZER_DIR,
    TOKENIZER_REF,
    TOKENIZER_REPORT_DIR,
    fail,
    load,
    setup_logging,
)

from carp.policies.sections import get_sections
from carp.studies import setting_study, tokenizer_studies
from carp.studies.data_efficiency import StudyLayout, add_referenced_studies, run_study, write_study_report
from carp.studies.point_replay import ReplaySetup, replay_point
from carp.tasks.base import ROLLOUTS
from carp.tracking.registry import registered_model_name

STUDIES = ("data_efficiency", "scales", "codebook", "tokenizers", "tokenizer_reuse")


def run_experiment(name: str, overrides: list[str], targets: tuple[str, ...] = ()) -> None:
    """`dvc exp run -n <name> -S ... [targets]` in the workspace; a leftover experiment of that name is removed first.

    `targets` (stage names) runs those stages and what they depend on only; none: the whole pipeline.
    """
    subprocess.run([sys.executable, "-m", "dvc", "exp", "remove", name], cwd=PROJECT_DIR, capture_output=True)
    arguments = [*(part for override in overrides for part in ("-S", override)), *targets]
    completed = subprocess.run([sys.executable, "-m", "dvc", "exp", "run", "-n", name, *arguments], cwd=PROJECT_DIR)
    if completed.returncode != 0:
        fail(f"`dvc exp run -n {name} {' '.join(arguments)}` exited with status {completed.returncode}")


def main() -> None:
    setup_logging()
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("study", choices=STUDIES)
    parser.add_argument(
        "--report-only", action="store_true", help="all but data_efficiency: run nothing, write the report"
    )
    args = parser.parse_args()
    params_file = PROJECT_DIR / "params.yaml"
    params = load(params_file)
    reuse = args.study == "tokenizer_reuse"
    key, scored = ("study.reuse_target_tasks", params.study.reuse_target_tasks) if reuse else ("tasks", params.tasks)
    try:
        offline = [task for task in scored if params.task(task).evaluation != ROLLOUTS]
        for task in params.study.reuse_source_tasks if reuse else ():
            params.task(task)  # a misspelt source task fails here, not in the source experiment
    except ValueError as error:
        fail(f"{params_file}: study: {error}")
    if offline:
        fail(f"{params_file}: {key}={list(scored)}: {offline} have no simulator; a study scores rollouts")
    layout = StudyLayout(params.tasks, params.policies, params.seeds)
    output_dir = REPORTS_DIR / "studies" / args.study
    references = {name: PROJECT_DIR / name for name in params.study.references}
    # A mistyped folder fails before hours of experiments; sizes a reference has not finished yet (another clone
    # still running its part) fail at the end, and the study run again then only writes the report.
    for name, folder in references.items():
        if not folder.is_dir():
            fail(f"{params_file}: study.references: {name}: no such study folder")
    if args.study != "data_efficiency":
        run_setting_study(args.study, params, params_file, layout, output_dir, list(references.values()), args)
        return
    original = params_file.read_text()
    try:
        points = run_study(params.study.data_efficiency_sizes, layout, EVAL_REPORT_DIR, output_dir, run_experiment)
    except FileNotFoundError as error:
        fail(str(error))
    finally:
        params_file.write_text(original)
    try:
        points, notes = add_referenced_studies(points, references, params.tasks)
    except (FileNotFoundError, ValueError) as error:
        fail(f"{params_file}: study.references: {error}")
    markdown = write_study_report(
        points, params.comparison.margin, params.comparison.alpha, output_dir, notes, params.comparison.min_seeds
    )
    print(f"wrote {markdown.relative_to(PROJECT_DIR)}")


def run_setting_study(name, params, params_file, layout, output_dir, references, args) -> None:
    """A study of one setting: its missing points as experiments, then the report over every folder."""
    marker = {"tasks": list(layout.tasks), "policies": list(layout.policies), "seeds": list(layout.seeds)}
    tasks = list(params.tasks)
    if name == "scales":
        study = setting_study.scales_study(params.study.scale_schedules, params.scales)
        if tuple(params.scales) not in study.values:
            fail(f"{params_file}: scales={list(params.scales)}: must be one of study.scale_schedules (the reference)")
    elif name == "codebook":
        study = setting_study.codebook_study(params.study.codebook_sizes, params.codebook_size)
        if params.codebook_size not in study.values:
            fail(f"{params_file}: codebook_size={params.codebook_size}: must be one of study.codebook_sizes")
    elif name == "tokenizers":
        if params.tokenizer.source != "pipeline":
            fail(f"{params_file}: tokenizer.source={params.tokenizer.source}: the tokenizers study trains each kind")
        lists = {"policies": params.policies, "register": params.register, "multitask": params.multitask}
        takes = tokenizer_studies.family_takes_kind(
            lambda family: getattr(get_sections(family)[0], "TOKENIZER_KINDS", None)
        )
        try:
            study = tokenizer_studies.tokenizer_study(params.study.tokenizer_kinds, lists, takes)
        except ValueError as error:
            fail(f"{params_file}: study.tokenizer_kinds: {error}")
    else:
        study, tasks, marker = reuse_study(params, output_dir, marker, args)
    if not args.report_only:
        data = params.data
        replay = ReplaySetup(
            RAW_DIR,
            PROCESSED_DIR,
            data.obs_steps,
            data.action_steps,
            data.action_horizon,
            params.study.replay_demos,
            params.eval.workers or os.cpu_count() or 1,
        )
        original = params_file.read_text()
        try:
            setting_study.run_points(
                study,
                marker,
                EVAL_REPORT_DIR,
                TOKENIZER_REPORT_DIR / "metrics.json",
                output_dir,
                run_experiment,
                TOKENIZER_DIR,
                lambda point_dir: replay_point(point_dir, tasks, replay),
            )
        except FileNotFoundError as error:
            fail(str(error))
        finally:
            params_file.write_text(original)
    try:
        points = setting_study.load_study(study, [output_dir, *references], tasks)
        markdown = setting_study.write_study_report(
            study, points, params.comparison.margin, params.comparison.alpha, output_dir, params.comparison.min_seeds
        )
    except (FileNotFoundError, ValueError) as error:
        fail(f"{params_file}: study.references: {error}")
    print(f"wrote {markdown.relative_to(PROJECT_DIR)}")


def reuse_study(params, output_dir, marker, args):
    """The reuse study's source tokenizer (trained and registered unless already), its arms, tasks and layout."""
    sources, targets = params.study.reuse_source_tasks, params.study.reuse_target_tasks
    spaces = {task: params.task(task).action_format(params.data.controller).space for task in (*sources, *targets)}
    if len(set(spaces.values())) > 1:
        fail(f"{PROJECT_DIR / 'params.yaml'}: study: the source and target tasks must share one action space: {spaces}")
    if not args.report_only:
        original = (PROJECT_DIR / "params.yaml").read_text()
        try:
            tokenizer_studies.run_source(
                sources,
                output_dir,
                lambda name, overrides: run_experiment(name, overrides, ("register_tokenizer",)),
                TOKENIZER_REPORT_DIR / "metrics.json",
                TOKENIZER_DIR,
                TOKENIZER_REF,
            )
        except FileNotFoundError as error:
            fail(str(error))
        finally:
            (PROJECT_DIR / "params.yaml").write_text(original)
    metrics_file = output_dir / tokenizer_studies.SOURCE_FOLDER / setting_study.TOKENIZER_METRICS
    source_metrics = json.loads(metrics_file.read_text()) if metrics_file.is_file() else {}
    name = registered_model_name(spaces[sources[0]], params.tokenizer.kind)
    uri = f"models:/{name}@{tokenizer_studies.REUSE_ALIAS}"
    study = tokenizer_studies.reuse_study(targets, sources, uri, source_metrics)
    return study, list(targets), tokenizer_studies.reuse_marker(marker, targets, sources)


if __name__ == "__main__":
    main()
