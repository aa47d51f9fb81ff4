"""What every pipeline stage script shares: paths, params, device, git/DVC context and the MLflow run.

torch is imported where it is used (and pandas by ``carp.outputs``), so the always-run ``check_inputs`` stage and the
data stages (collect, ingest), which need neither, start seconds sooner.
"""

import argparse
import dataclasses
import logging
import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from carp.config import ConfigError, Params, flatten_params, load_params
from carp.outputs import MULTITASK_SUFFIX

if TYPE_CHECKING:
    import torch

    from carp.data.rendering import RenderSettings

logger = logging.getLogger("carp.pipeline")

PROJECT_DIR = Path(__file__).resolve().parents[1]

# Fixed, untimestamped artifact paths (declared in dvc.yaml).
RAW_DIR = PROJECT_DIR / "data" / "raw"
PROCESSED_DIR = PROJECT_DIR / "data" / "processed"
# Data outputs are built here, then renamed into place: on their filesystem (the rename is atomic) and outside every
# path a stage declares as a dependency, so a killed stage's leftover never enters another stage's hash in dvc.lock.
STAGING_DIR = PROJECT_DIR / "data" / ".staging"
TOKENIZER_DIR = PROJECT_DIR / "models" / "tokenizer"
TOKENIZER_REF = PROJECT_DIR / "models" / "tokenizer_ref.json"
POLICY_DIR = PROJECT_DIR / "models" / "policy"
POLICY_REF_DIR = PROJECT_DIR / "models" / "policy_ref"
REPORTS_DIR = PROJECT_DIR / "reports"
TOKENIZER_REPORT_DIR = REPORTS_DIR / "tokenizer"
POLICY_REPORT_DIR = REPORTS_DIR / "policy"
EVAL_REPORT_DIR = REPORTS_DIR / "eval"
EVAL_VIDEO_DIR = EVAL_REPORT_DIR / "videos"
# Training states for resuming after an interruption; not DVC outputs (DVC deletes outputs before a stage runs).
CHECKPOINT_DIR = PROJECT_DIR / "checkpoints"


def project_root() -> Path:
    """The user's workspace, even when DVC runs the stage in a temporary copy (``dvc exp run --temp/--queue``).

    DVC's temporary workspaces live under ``<root>/.dvc/tmp/exps/``; MLflow and Optuna stores must stay in ``<root>``
    so that runs made there land in the project's store.
    """
    parts = PROJECT_DIR.parts
    for index in range(len(parts) - 2):
        if parts[index : index + 3] == (".dvc", "tmp", "exps"):
            return Path(*parts[:index])
    return PROJECT_DIR


def parse_args(description: str, per_task: bool = False) -> argparse.Namespace:
    """Common command line: ``--params``, and ``--task`` for per-task stages (per-family ones: `policy_stage_args`)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--params", type=Path, default=PROJECT_DIR / "params.yaml")
    if per_task:
        parser.add_argument("--task", required=True)
    return parser.parse_args()


def policy_stage_args(description: str, task_or_multitask: bool = False) -> tuple[argparse.Namespace, Params]:
    """Command line and params of a per-(task, family, seed) stage; one line and exit 1 when one is not listed.

    ``--multitask`` names the family's multi-task policy (listed in ``multitask``) instead of its single-task one
    (listed in ``policies``). With `task_or_multitask` (training) it stands instead of ``--task``: that policy trains
    on every task; otherwise ``--task`` names the task it is evaluated on.
    """
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--params", type=Path, default=PROJECT_DIR / "params.yaml")
    task_options = parser.add_mutually_exclusive_group(required=True) if task_or_multitask else parser
    task_options.add_argument("--task", required=not task_or_multitask)
    task_options.add_argument("--multitask", action="store_true", help="the family's multi-task policy")
    parser.add_argument("--policy", required=True, help="a policy family listed in `policies` (or `multitask`)")
    parser.add_argument("--seed", type=int, required=True, help="a training seed listed in `seeds`")
    args = parser.parse_args()
    params = load(args.params)
    key, listed = ("multitask", params.multitask) if args.multitask else ("policies", params.policies)
    if args.policy not in listed:
        fail(f"{args.params}: {key}={list(listed)}: --policy {args.policy} is not listed")
    if args.seed not in params.seeds:
        fail(f"{args.params}: seeds={list(params.seeds)}: --seed {args.seed} is not listed")
    if args.task is not None and args.task not in params.tasks:
        fail(f"{args.params}: tasks={list(params.tasks)}: --task {args.task} is not listed")
    return args, params


def camera_settings(params: Params) -> "RenderSettings | None":
    """The cameras ingest renders and an image policy's rollouts render, alike; None for state observations.

    Selects MuJoCo's offscreen backend first (MuJoCo reads ``MUJOCO_GL`` when first imported; spawned workers
    inherit it).
    """
    if params.data.observations != "image":
        return None
    from carp.data.rendering import RenderSettings, offscreen_backend

    os.environ.setdefault("MUJOCO_GL", offscreen_backend())
    return RenderSettings(cameras=params.data.cameras, image_size=params.data.image_size)


def seed_name(seed: int) -> str:
    """``seed<seed>``: the path part of one training seed's outputs."""
    return f"seed{seed}"


def policy_dir(task: str, policy: str, seed: int) -> Path:
    """``models/policy/<task>/<policy>/seed<seed>``: the checkpoint ``policy.pt`` (and ``snapshots/``) of one run."""
    return POLICY_DIR / task / policy / seed_name(seed)


def policy_report_dir(task: str, policy: str, seed: int) -> Path:
    """``reports/policy/<task>/<policy>/seed<seed>``: training history and metrics of one run."""
    return POLICY_REPORT_DIR / task / policy / seed_name(seed)


MULTITASK_DIRNAME = "multitask"
"""The part of a multi-task policy's paths that stands for the task: ``models/policy/multitask/<policy>/...``."""


def multitask_label(policy: str) -> str:
    """``<policy>-multitask``: a family's multi-task policy in evaluation paths and the report, beside ``<policy>``."""
    return policy + MULTITASK_SUFFIX


def stage_policy_paths(args: argparse.Namespace) -> tuple[Path, Path, str]:
    """The checkpoint directory, training report directory and label of a policy stage's ``--policy --seed``.

    A single-task policy's are ``policy_dir``, ``policy_report_dir`` and the family; a multi-task one's
    (``--multitask``) sit under ``multitask/`` in place of the task, and its label is ``multitask_label``.
    """
    return policy_paths(args.task, args.policy, args.seed, args.multitask)


def policy_paths(task: str | None, family: str, seed: int, multitask: bool) -> tuple[Path, Path, str]:
    """The checkpoint directory, training report directory and label of `family`'s policy at training `seed`: its
    single-task policy on `task`, or with `multitask` its multi-task policy (`task` unused)."""
    if multitask:
        return (
            POLICY_DIR / MULTITASK_DIRNAME / family / seed_name(seed),
            POLICY_REPORT_DIR / MULTITASK_DIRNAME / family / seed_name(seed),
            multitask_label(family),
        )
    return policy_dir(task, family, seed), policy_report_dir(task, family, seed), family


def evaluation_report(task: str, policy: str, seed: int) -> Path:
    """``reports/eval/<task>/<policy>/seed<seed>.json``: evaluation summary of one run (episodes beside it).

    `policy` is a family, or a family's `multitask_label` for its multi-task policy evaluated on `task`.
    """
    return EVAL_REPORT_DIR / task / policy / f"{seed_name(seed)}.json"


def policy_reference(task: str, policy: str, seed: int) -> Path:
    """``models/policy_ref/<task>/<policy>/seed<seed>.json``: the registered version of one run (register_policy)."""
    return POLICY_REF_DIR / task / policy / f"{seed_name(seed)}.json"


def load(path: Path) -> Params:
    """Load params or exit non-zero with the one-line validation message."""
    try:
        return load_params(path)
    except ConfigError as error:
        fail(str(error))


def fail(message: str) -> None:
    """Print a one-line error and exit with status 1."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(1)


def select_device(params: Params) -> "torch.device":
    """``auto`` picks CUDA when present; an explicit ``cuda`` without a GPU is an error."""
    import torch

    if params.device == "cuda" and not torch.cuda.is_available():
        fail("device=cuda but no CUDA device is available (set device: auto or cpu)")
    if params.device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(params.device)


def git_commit() -> str:
    """HEAD's commit of the project, or ``unknown`` outside a git checkout."""
    try:
        return subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=PROJECT_DIR, capture_output=True, text=True, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def dvc_experiment_name() -> str:
    """Name of the DVC experiment running this stage (DVC exports ``DVC_EXP_NAME``), or empty."""
    return os.environ.get("DVC_EXP_NAME", "")


def tracking_uri(params: Params) -> str:
    """The params' tracking URI with relative SQLite paths anchored at the project root."""
    from carp.tracking.runs import resolve_tracking_uri

    return resolve_tracking_uri(params.tracking.uri, project_root())


@contextmanager
def mlflow_stage(params: Params, stage: str, experiment: str, extra_tags: dict | None = None) -> Iterator:
    """An MLflow run for this stage, tagged with commit, stage, DVC experiment and params hash."""
    from carp.tracking.runs import stage_run

    tags = {
        "carp.git_commit": git_commit(),
        "carp.dvc_stage": stage,
        "carp.dvc_experiment": dvc_experiment_name(),
        **(extra_tags or {}),
    }
    with stage_run(
        tracking_uri(params),
        experiment_name=f"{params.tracking.experiment_prefix}-{experiment}",
        run_name=stage,
        flat_params=flatten_params(params),
        tags=tags,
    ) as run:
        yield run


def copy_fields(target_type: type, *sources: object, **overrides):
    """Build the library dataclass ``target_type`` from same-named fields of typed param sections.

    Params sections and the library's specs/settings share field names (``epochs``, ``depth``, ...); this keeps the
    mapping in one place instead of a hand-written keyword list per stage. Later sources and ``overrides`` win.
    """
    names = {field.name for field in dataclasses.fields(target_type)}
    values = {}
    for source in sources:
        values.update({name: getattr(source, name) for name in names if hasattr(source, name)})
    return target_type(**{**values, **overrides})


def setup_logging() -> None:
    """INFO logs to stderr; tqdm bars print there too."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s", stream=sys.stderr)
