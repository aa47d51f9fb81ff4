"""The import graph of `src/carp` and `pipeline/`, and what it says about `dvc.yaml` and the library's layers.

Every import that can run counts, the ones inside functions included: a stage that imports a module only when a
branch runs still runs that module's code in some configuration, so its results depend on the file. So does a string
naming a module (`"carp.tasks.lift.task:TASK"`, `"carp.policies.carp.family:FAMILY"`): the task and family registries
import their entries by name. Imports under `if TYPE_CHECKING:` never run and do not count. Importing `carp.a.b` also
runs `carp/__init__.py` and `carp/a/__init__.py`, which count as reached for the stages' dependencies (but not as
imports between modules, where they would join every module of a package).

    .venv/bin/python tools/import_graph.py deps     # files each stage reaches that its dvc.yaml deps do not cover
    .venv/bin/python tools/import_graph.py deps --write   # rewrite each stage's code deps in dvc.yaml from the graph
    .venv/bin/python tools/import_graph.py cycles   # import circles among the library's modules
    .venv/bin/python tools/import_graph.py layers   # imports from a lower layer up to a higher one
"""

import argparse
import ast
import fnmatch
import re
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import networkx as nx
import yaml

REPO = Path(__file__).resolve().parents[1]
LIBRARY = Path("src/carp")
PIPELINE = Path("pipeline")

LAYERS: tuple[tuple[str, ...], ...] = (
    ("carp", "carp.outputs", "carp.config.checks", "carp.training.checkpoint", "carp.serving.protocol"),
    ("carp.tasks", "carp.data"),
    ("carp.config", "carp.config_docs", "carp.policies.sections", "carp.policies.*.config"),
    (
        "carp.tokenizer",
        "carp.vision",
        "carp.policies.base",
        "carp.policies.policy_family",
        "carp.policies.checkpoint_files",
    ),
    (
        "carp.training.runtime",
        "carp.training.loop",
        "carp.training.run",
        "carp.training.distributed",
        "carp.training.cross_entropy",
    ),
    ("carp.policies",),
    ("carp.training", "carp.evaluation", "carp.tracking"),
    ("carp.reporting", "carp.sweep", "carp.studies", "carp.serving", "carp.cli"),
)
"""The library's layers from the bottom up (docs/architecture.md): a module may import its own layer and those below.

A module belongs to the layer of the most specific entry that names it: the entry itself or a module under it, with
`*` standing for one name (`carp.policies.*.config`: each family's params sections). `carp` itself is the package's
`__init__` (its version)."""


@dataclass(frozen=True)
class ImportGraph:
    """Files (relative to the repository) and the files each one imports, function-level imports included."""

    edges: Mapping[Path, frozenset[Path]]
    with_packages: Mapping[Path, frozenset[Path]]

    @classmethod
    def build(cls, repo: Path = REPO) -> "ImportGraph":
        """The graph of every file under `src/carp` and `pipeline/` of `repo`."""
        files = sorted((repo / LIBRARY).rglob("*.py")) + sorted((repo / PIPELINE).glob("*.py"))
        return cls(
            {file.relative_to(repo): frozenset(_imported_files(file, repo, packages=False)) for file in files},
            {file.relative_to(repo): frozenset(_imported_files(file, repo, packages=True)) for file in files},
        )

    def reached(self, start: Path) -> set[Path]:
        """Every file `start` runs when it runs: itself and what it imports (packages' `__init__` too), transitively."""
        seen, stack = {start}, [start]
        while stack:
            for imported in self.with_packages.get(stack.pop(), ()):
                if imported not in seen:
                    seen.add(imported)
                    stack.append(imported)
        return seen

    def library_graph(self) -> nx.DiGraph:
        """Module -> module it imports by name, among `src/carp` (a package's `__init__` is the package's node)."""
        graph = nx.DiGraph()
        for source, targets in self.edges.items():
            if not source.is_relative_to(LIBRARY):
                continue
            graph.add_node(module_name(source))
            for target in targets:
                if target.is_relative_to(LIBRARY) and target != source:
                    graph.add_edge(module_name(source), module_name(target))
        return graph


def module_name(path: Path) -> str:
    """`src/carp/data/ingest.py` -> `carp.data.ingest`; a package's `__init__.py` -> the package."""
    parts = path.relative_to("src").with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULE_STRING = re.compile(r"(carp(?:\.\w+)+)(?::\w+)?")
"""A string naming a library module, alone or with an attribute (`module:attribute`), as the registries hold them."""


def _imported_files(file: Path, repo: Path, packages: bool) -> set[Path]:
    """The repository files `file` imports, by statement or by a module-naming string.

    With `packages`, each package `__init__` on the way counts too; without, an import names one file: the module, or
    the package's `__init__` when it imports a name the package defines.
    """
    tree = ast.parse(file.read_text(), filename=str(file))
    package = _package_of(file, repo)
    found: set[Path] = set()
    typing_only = {id(node) for block in ast.walk(tree) if _is_type_checking_block(block) for node in ast.walk(block)}
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            match = MODULE_STRING.fullmatch(node.value)
            names = [match.group(1)] if match else []
        elif isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _absolute(node.module, node.level, package)
            if base is None:
                continue
            submodules = [f"{base}.{alias.name}" for alias in node.names if alias.name != "*"]
            names = [base, *submodules] if packages else [name for name in submodules if _files_of(name, file, repo)]
            if not packages and len(names) < len(submodules) or not submodules:
                names.append(base)
        else:
            continue
        for name in names:
            files = _files_of(name, file, repo)
            found |= set(files if packages else files[-1:])
    return found


def _is_type_checking_block(node: ast.AST) -> bool:
    """`if TYPE_CHECKING:`: imports for annotations only, which never run."""
    return isinstance(node, ast.If) and (
        (isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING")
        or (isinstance(node.test, ast.Attribute) and node.test.attr == "TYPE_CHECKING")
    )


def _package_of(file: Path, repo: Path) -> str | None:
    relative = file.relative_to(repo)
    if not relative.is_relative_to("src"):
        return None
    parts = relative.relative_to("src").parent.parts
    return ".".join(parts)


def _absolute(module: str | None, level: int, package: str | None) -> str | None:
    if level == 0:
        return module
    if package is None:
        return None
    parts = package.split(".")
    base = parts[: len(parts) - level + 1]
    return ".".join(base + ([module] if module else []))


def _files_of(name: str, importer: Path, repo: Path) -> list[Path]:
    """The files that importing the dotted `name` runs, outermost first: each package's `__init__`, then the module."""
    parts = name.split(".")
    if parts[0] == "carp":
        root = repo / "src"
    elif len(parts) == 1 and (repo / PIPELINE / f"{name}.py").exists() and importer.parent == repo / PIPELINE:
        return [PIPELINE / f"{name}.py"]
    else:
        return []
    files = []
    for depth in range(1, len(parts) + 1):
        base = root.joinpath(*parts[:depth])
        if (base / "__init__.py").exists():
            files.append((base / "__init__.py").relative_to(repo))
        elif base.with_suffix(".py").exists():
            files.append(base.with_suffix(".py").relative_to(repo))
            break
        else:
            break
    return files


def stage_scripts(dvc_yaml: Path = REPO / "dvc.yaml") -> dict[str, tuple[Path, list[str]]]:
    """Stage name -> (the pipeline script its command runs, its listed deps) for every stage of `dvc.yaml`."""
    stages = yaml.safe_load(dvc_yaml.read_text())["stages"]
    found = {}
    for name, stage in stages.items():
        body = stage.get("do", stage)
        match = re.search(r"python (pipeline/\w+\.py)", body["cmd"])
        if match is None:
            raise ValueError(f"{dvc_yaml}: stage {name!r} runs no pipeline script: {body['cmd']!r}")
        deps = [dep for dep in body.get("deps", ()) if isinstance(dep, str)]
        found[name] = (Path(match.group(1)), deps)
    return found


def uncovered(reached: Iterable[Path], deps: Sequence[str]) -> list[Path]:
    """The reached files that no listed dep (a file, or a folder above it) covers."""
    listed = [Path(dep.rstrip("/")) for dep in deps if "${" not in dep]
    return sorted(file for file in reached if not any(file == dep or file.is_relative_to(dep) for dep in listed))


def missing_deps(graph: ImportGraph, dvc_yaml: Path = REPO / "dvc.yaml") -> dict[str, list[Path]]:
    """Stage -> the library and pipeline files it reaches that `dvc.yaml` does not list; only stages with some."""
    missing = {}
    for stage, (script, deps) in stage_scripts(dvc_yaml).items():
        files = uncovered(graph.reached(script), deps)
        if files:
            missing[stage] = files
    return missing


def code_deps(graph: ImportGraph, script: Path, repo: Path = REPO) -> list[str]:
    """What a stage running `script` lists as code.

    The script, the pipeline helpers it imports, then the library files it reaches, sorted; a folder whose every
    Python file it reaches is listed as the folder.
    """
    reached = graph.reached(script)
    helpers = sorted(file.as_posix() for file in reached if file.is_relative_to(PIPELINE) and file != script)
    library = [file for file in reached if file.is_relative_to(LIBRARY)]
    return [script.as_posix(), *helpers, *sorted(_grouped(LIBRARY, set(library), repo))]


def _grouped(folder: Path, reached: set[Path], repo: Path) -> list[str]:
    """The reached files under `folder`, each subfolder whose every file is reached named as the subfolder."""
    listed = []
    for child in sorted((repo / folder).iterdir()):
        relative = child.relative_to(repo)
        if child.is_dir() and (child / "__init__.py").exists():
            files = {file.relative_to(repo) for file in child.rglob("*.py")}
            if files <= reached:
                listed.append(relative.as_posix())
            elif files & reached:
                listed += _grouped(relative, reached, repo)
        elif relative in reached:
            listed.append(relative.as_posix())
    return listed


def write_code_deps(graph: ImportGraph, dvc_yaml: Path = REPO / "dvc.yaml") -> None:
    """Replace each stage's code deps (`src/carp/...`, `pipeline/...`) in `dvc_yaml` with `code_deps`.

    The new list takes the place of the first code dep; other deps, comments and layout stay as they are.
    """
    scripts = stage_scripts(dvc_yaml)
    lines, stage, in_deps, written = [], None, False, set()
    for line in dvc_yaml.read_text().splitlines():
        if match := re.match(r"^  (\w+):\s*$", line):
            stage = match.group(1)
        if re.match(r"^\s+deps:\s*$", line):
            in_deps = True
        elif in_deps and (entry := re.match(r"^(\s+)- (src/carp\S*|pipeline/\S+)$", line)):
            if stage not in written:
                written.add(stage)
                lines += [f"{entry.group(1)}- {dep}" for dep in code_deps(graph, scripts[stage][0], dvc_yaml.parent)]
            continue
        elif in_deps and not re.match(r"^\s+(- |#)", line):
            in_deps = False
        lines.append(line)
    dvc_yaml.write_text("\n".join(lines) + "\n")


def layer_of(module: str) -> int:
    """Index in `LAYERS` of the most specific entry naming `module` (see `LAYERS`)."""
    best, best_length = None, -1
    for index, layer in enumerate(LAYERS):
        for entry in layer:
            names = entry == "carp" and module == "carp"
            names = names or (
                entry != "carp" and any(fnmatch.fnmatchcase(module, pattern) for pattern in (entry, f"{entry}.*"))
            )
            if names and len(entry) > best_length:
                best, best_length = index, len(entry)
    if best is None:
        raise ValueError(f"{module} belongs to no layer of tools/import_graph.py LAYERS")
    return best


def upward_imports(graph: nx.DiGraph) -> list[tuple[str, str]]:
    """(importer, imported) pairs where a module imports from a layer above its own."""
    return sorted((source, target) for source, target in graph.edges if layer_of(target) > layer_of(source))


def cycles(graph: nx.DiGraph) -> list[list[str]]:
    """The strongly connected groups of more than one module: each holds at least one import circle."""
    return sorted(sorted(group) for group in nx.strongly_connected_components(graph) if len(group) > 1)


def main() -> None:
    """Print the problems of one check, one per line; exit 1 when there are any."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("check", choices=("deps", "cycles", "layers"))
    parser.add_argument("--write", action="store_true", help="with deps: rewrite the code deps in dvc.yaml")
    arguments = parser.parse_args()
    check = arguments.check
    graph = ImportGraph.build()
    if check == "deps" and arguments.write:
        write_code_deps(graph)
    if check == "deps":
        problems = [f"{stage}: {file}" for stage, files in missing_deps(graph).items() for file in files]
    elif check == "cycles":
        problems = [" <-> ".join(group) for group in cycles(graph.library_graph())]
    else:
        problems = [f"{source} -> {target}" for source, target in upward_imports(graph.library_graph())]
    print("\n".join(problems) or f"no {check} problems")
    sys.exit(1 if problems else 0)


if __name__ == "__main__":
    main()
