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
"""

import argparse
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
    TOKENIZER_REPORT_DIR,
    fail,
    load,
    setup_logging,
)

from carp.studies import setting_study
from carp.studies.data_efficiency import StudyLayout, add_referenced_studies, run_study, write_study_report
from carp.studies.point_replay import ReplaySetup, replay_point
from carp.tasks.base import ROLLOUTS

STUDIES = ("data_efficiency", "scales", "codebook")


def run_experiment(name: str, overrides: list[str]) -> None:
    """`dvc exp run -n <name> -S ...` in the workspace; a leftover experiment of that name is removed first."""
    subprocess.run([sys.executable, "-m", "dvc", "exp", "remove", name], cwd=PROJECT_DIR, capture_output=True)
    arguments = [part for override in overrides for part in ("-S", override)]
    completed = subprocess.run([sys.executable, "-m", "dvc", "exp", "run", "-n", name, *arguments], cwd=PROJECT_DIR)
    if completed.returncode != 0:
        fail(f"`dvc exp run -n {name} {' '.join(arguments)}` exited with status {completed.returncode}")


def main() -> None:
    setup_logging()
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("study", choices=STUDIES)
    parser.add_argument("--report-only", action="store_true", help="scales, codebook: run nothing, write the report")
    args = parser.parse_args()
    params_file = PROJECT_DIR / "params.yaml"
    params = load(params_file)
    offline = [task for task in params.tasks if params.task(task).evaluation != ROLLOUTS]
    if offline:
        fail(f"{params_file}: tasks={list(params.tasks)}: {offline} have no simulator; a study scores rollouts")
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
    """The scales or codebook study: its missing points as experiments, then the report over every folder."""
    if name == "scales":
        study = setting_study.scales_study(params.study.scale_schedules, params.scales)
        if tuple(params.scales) not in study.values:
            fail(f"{params_file}: scales={list(params.scales)}: must be one of study.scale_schedules (the reference)")
    else:
        study = setting_study.codebook_study(params.study.codebook_sizes, params.codebook_size)
        if params.codebook_size not in study.values:
            fail(f"{params_file}: codebook_size={params.codebook_size}: must be one of study.codebook_sizes")
    if not args.report_only:
        marker = {"tasks": list(layout.tasks), "policies": list(layout.policies), "seeds": list(layout.seeds)}
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
                lambda point_dir: replay_point(point_dir, layout.tasks, replay),
            )
        except FileNotFoundError as error:
            fail(str(error))
        finally:
            params_file.write_text(original)
    try:
        points = setting_study.load_study(study, [output_dir, *references], params.tasks)
        markdown = setting_study.write_study_report(
            study, points, params.comparison.margin, params.comparison.alpha, output_dir, params.comparison.min_seeds
        )
    except (FileNotFoundError, ValueError) as error:
        fail(f"{params_file}: study.references: {error}")
    print(f"wrote {markdown.relative_to(PROJECT_DIR)}")


if __name__ == "__main__":
    main()
