"""`make dry` and `make dry-exp`: DVC's dry run that also answers before the pipeline's first run.

DVC 3's dry run asks its run cache about every stage it would run, and the run cache hashes the stage's dependencies
first: a dependency that an upstream stage has not produced yet (on a fresh clone, `data/inputs/<task>.json`,
`data/raw/<task>.hdf5`, ...) raises FileNotFoundError and the dry run stops at the second stage (DVC issue 9818).
A stage with a missing dependency cannot have a run-cache entry, so in this process the run cache answers "not
cached" for it, which is what DVC does for any other uncached stage; then DVC's own command line runs, always with
`--dry`. Nothing is installed anywhere: other DVC processes and real runs are untouched.

    python tools/dvc_dry.py repro [targets ...]                  # dvc repro --dry
    python tools/dvc_dry.py exp run [-S key=value ...]          # dvc exp run --dry
"""

import sys
from types import ModuleType

DRY_COMMANDS = {("repro",): 1, ("exp", "run"): 2}
"""DVC commands this script runs dry, and how many words name them."""


def patch_stage_cache(module: ModuleType) -> None:
    """Make `StageCache.restore` report "not cached" in dry runs of a stage with a missing local dependency."""
    stage_cache = module.StageCache
    if getattr(stage_cache.restore, "carp_dry_run_patch", False):
        return
    original = stage_cache.restore

    def restore(self, stage, run_cache=True, pull=False, dry=False):
        if dry and any(dep.protocol == "local" and not dep.exists for dep in stage.deps):
            raise module.RunCacheNotFoundError(stage)
        return original(self, stage, run_cache=run_cache, pull=pull, dry=dry)

    restore.carp_dry_run_patch = True  # type: ignore[attr-defined]
    stage_cache.restore = restore


def dry_arguments(argv: list[str]) -> list[str]:
    """The DVC command line of `argv` with `--dry` added after the command; one `error:` line for another command."""
    for words, length in DRY_COMMANDS.items():
        if tuple(argv[:length]) == words:
            rest = [argument for argument in argv[length:] if argument != "--dry"]
            return [*words, "--dry", *rest]
    known = " or ".join(f"`{' '.join(words)}`" for words in DRY_COMMANDS)
    raise SystemExit(f"error: tools/dvc_dry.py: {' '.join(argv[:2]) or 'no command'}: must start with {known}")


def main(argv: list[str]) -> int:
    """Patch this process's DVC run cache, then run DVC's command line dry."""
    arguments = dry_arguments(argv)
    import dvc.stage.cache
    from dvc.cli import main as dvc_main

    patch_stage_cache(dvc.stage.cache)
    return dvc_main(arguments)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
