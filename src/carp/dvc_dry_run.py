"""Lets `dvc repro --dry` and `dvc exp run --dry` answer before the pipeline's first run.

DVC 3's dry run asks its run cache about every stage it would run, and the run cache hashes the stage's dependencies
first: a dependency that an upstream stage has not produced yet (on a fresh clone, `data/inputs/<task>.json`,
`data/raw/<task>.hdf5`, ...) raises FileNotFoundError and the dry run stops at the second stage (DVC issue 9818).
A stage with a missing dependency cannot have a run-cache entry, so this module makes the run cache answer "not
cached" for it in dry runs, which is what DVC does for any other uncached stage; real runs are untouched.

`make setup` installs a `.pth` file (`tools/carp-dvc-dry-run.pth`) that calls :func:`install` when the project's
Python starts, and does nothing where the `carp` on the path has no such module (another checkout or an older commit
using the same venv); the patch is applied only if and when DVC's `dvc.stage.cache` is imported, so other programs
pay nothing.
"""

import importlib.abc
import importlib.util
import sys
from types import ModuleType

TARGET = "dvc.stage.cache"


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


class _PatchAfterImport(importlib.abc.MetaPathFinder):
    """Finds `dvc.stage.cache` through the other finders and patches it once its code has run."""

    def find_spec(self, fullname, path, target=None):
        if fullname != TARGET:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None and spec.loader is not None:
                break
        else:
            return None
        execute = spec.loader.exec_module

        def exec_module(module: ModuleType) -> None:
            execute(module)
            patch_stage_cache(module)

        spec.loader.exec_module = exec_module  # type: ignore[method-assign]
        return spec


def install() -> None:
    """Patch DVC's run cache now if it is loaded, else as soon as it is imported (idempotent)."""
    if TARGET in sys.modules:
        patch_stage_cache(sys.modules[TARGET])
    elif not any(isinstance(finder, _PatchAfterImport) for finder in sys.meta_path):
        sys.meta_path.insert(0, _PatchAfterImport())
