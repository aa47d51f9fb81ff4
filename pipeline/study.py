"""Run one of the paper's studies as DVC experiments in this workspace (`make study STUDY=data_efficiency`).

data_efficiency: one experiment per size of `study.data_efficiency_sizes` (`dvc exp run -n data-efficiency-<N> -S
data.num_demos=<largest> -S data.subset_size=<N>`), each size's evaluations copied into
reports/studies/data_efficiency/size<N>/, then reports/studies/data_efficiency/report.md and report.html. Run it again
after an interruption: finished sizes are not run again. params.yaml is put back as it was when the study ends.
The report adds the families of the study folders in `study.references` (the same study run in other clones).
"""

import argparse
import subprocess
import sys

from stage_support import EVAL_REPORT_DIR, PROJECT_DIR, REPORTS_DIR, fail, load, setup_logging

from carp.studies.data_efficiency import StudyLayout, add_referenced_studies, run_study, write_study_report

STUDIES = ("data_efficiency",)


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
    args = parser.parse_args()
    params_file = PROJECT_DIR / "params.yaml"
    params = load(params_file)
    layout = StudyLayout(params.tasks, params.policies, params.seeds)
    output_dir = REPORTS_DIR / "studies" / args.study
    references = {name: PROJECT_DIR / name for name in params.study.references}
    # A mistyped folder fails before hours of experiments; sizes a reference has not finished yet (another clone
    # still running its part) fail at the end, and the study run again then only writes the report.
    for name, folder in references.items():
        if not folder.is_dir():
            fail(f"{params_file}: study.references: {name}: no such study folder")
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


if __name__ == "__main__":
    main()
