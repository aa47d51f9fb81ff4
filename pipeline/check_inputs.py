"""check_inputs stage (runs on every `dvc repro` / `dvc exp run`): validate params.yaml, record each task's source.

DVC reruns a stage only when a dependency it tracks changed, so a typo in a key no stale stage reads (``foo: 1``,
``policy.epoch: 3``) would otherwise pass as "up to date". This stage is ``always_changed`` and every other stage
lies downstream of it, so the whole params file is validated before anything runs. It also writes
``data/inputs/<task>.json`` (see :mod:`carp.data.sources`), collect's dependency on the user's own demo file, and
``data/inputs/teachers/<family>.json`` for each listed policy family: the params section of the teacher family it
distils (`consistency_policy` trains its `edm_unet` teacher in its own train_policy stage), or null. DVC's matrix
gives every train_policy stage the same params keys, so this file is how a teacher's section reaches its student's
stage alone: a change to `edm_unet` reruns the student's training and no other family's.
"""

import dataclasses
import json
import os
import shutil

from stage_support import PROJECT_DIR, fail, load, parse_args

from carp.data.sources import SourceError, describe_source
from carp.policies.sections import teacher_of

INPUTS_DIR = PROJECT_DIR / "data" / "inputs"
TEACHERS_DIRNAME = "teachers"


def main() -> None:
    params_file = parse_args(__doc__).params
    params = load(params_file)
    try:
        # An image run's cameras: collect decodes a LeRobotDataset's videos for them.
        cameras = params.data.cameras if params.data.image_keys else ()
        records = {
            task: describe_source(task, params.data.raw_files.get(task), PROJECT_DIR, cameras, params.data.image_size)
            for task in params.tasks
        }
    except SourceError as error:
        fail(f"{params_file}: {error}")
    # A fixed staging name: a run killed mid-write leaves nothing that the next run does not clear first.
    staging = INPUTS_DIR.with_name(f".{INPUTS_DIR.name}.tmp")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    for task, record in records.items():
        (staging / f"{task}.json").write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")
    (staging / TEACHERS_DIRNAME).mkdir()
    for family in params.policies:
        teacher = teacher_of(family)
        section = None if teacher is None else {teacher: dataclasses.asdict(params.family_config(teacher))}
        (staging / TEACHERS_DIRNAME / f"{family}.json").write_text(json.dumps(section, indent=2, sort_keys=True) + "\n")
    shutil.rmtree(INPUTS_DIR, ignore_errors=True)
    os.replace(staging, INPUTS_DIR)
    sources = ", ".join(f"{task}: {record['source']}" for task, record in records.items())
    print(f"{params_file.name} is valid; demonstration sources: {sources}")


if __name__ == "__main__":
    main()
