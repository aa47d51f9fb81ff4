"""The import graph (`tools/import_graph.py`): what counts as an import, and dvc.yaml's code deps against it."""

import importlib.util
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "tools" / "import_graph.py"


def _load_tool():
    spec = importlib.util.spec_from_file_location("import_graph", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules["import_graph"] = module  # dataclasses resolve the module by name
    spec.loader.exec_module(module)
    return module


tool = _load_tool()


@pytest.fixture(scope="module")
def repo_graph():
    return tool.ImportGraph.build()


def test_every_stage_lists_the_library_and_pipeline_files_it_reaches(repo_graph):
    missing = tool.missing_deps(repo_graph)
    assert missing == {}, "run `.venv/bin/python tools/import_graph.py deps --write`: " + "; ".join(
        f"{stage} misses {', '.join(map(str, files))}" for stage, files in missing.items()
    )


def test_the_deps_written_are_what_the_graph_derives(repo_graph):
    for stage, (script, deps) in tool.stage_scripts().items():
        listed = [dep for dep in deps if dep.startswith(("src/carp", "pipeline/"))]
        assert listed == tool.code_deps(repo_graph, script), stage


def _write(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


@pytest.fixture
def toy_repo(tmp_path):
    _write(
        tmp_path,
        {
            "src/carp/__init__.py": "",
            "src/carp/base.py": "VALUE = 1\n",
            "src/carp/table.py": 'ENTRIES = {"a": "carp.pkg.heavy:THING"}\n',
            "src/carp/pkg/__init__.py": "from carp.pkg.light import NAME\n",
            "src/carp/pkg/light.py": "from carp.base import VALUE\nNAME = VALUE\n",
            "src/carp/pkg/heavy.py": "def load():\n    from carp.user import use\n    return use\n",
            "src/carp/user.py": "from carp import table\n\ndef use():\n    return table\n",
            "src/carp/unused.py": "",
            "pipeline/helper.py": "from carp.pkg.light import NAME\n",
            "pipeline/stage.py": "import json\nfrom helper import NAME\nfrom carp.base import VALUE\n",
            "pipeline/other.py": "from carp.table import ENTRIES\n",
            "dvc.yaml": (
                "stages:\n"
                "  first:\n"
                "    cmd: python pipeline/stage.py --flag\n"
                "    deps:\n"
                "      - data/raw\n"
                "      # the script\n"
                "      - pipeline/stage.py\n"
                "      - src/carp/base.py\n"
                "    outs:\n"
                "      - out\n"
                "  second:\n"
                "    foreach: ${tasks}\n"
                "    do:\n"
                "      cmd: python pipeline/other.py --task ${item}\n"
                "      deps:\n"
                "        - pipeline/other.py\n"
                "        - src/carp\n"
            ),
        },
    )
    return tmp_path


def test_lazy_imports_module_strings_and_package_inits_are_reached(toy_repo):
    graph = tool.ImportGraph.build(toy_repo)
    reached = {path.as_posix() for path in graph.reached(Path("pipeline/stage.py"))}
    assert reached == {
        "pipeline/stage.py",
        "pipeline/helper.py",
        "src/carp/__init__.py",
        "src/carp/base.py",
        "src/carp/pkg/__init__.py",
        "src/carp/pkg/light.py",
    }
    # The table names a module by string; that module imports its user inside a function: both count.
    through_table = {path.as_posix() for path in graph.reached(Path("pipeline/other.py"))}
    assert {"src/carp/table.py", "src/carp/pkg/heavy.py", "src/carp/user.py"} <= through_table
    assert "src/carp/unused.py" not in through_table


def test_uncovered_files_and_the_rewritten_deps(toy_repo):
    graph = tool.ImportGraph.build(toy_repo)
    missing = tool.missing_deps(graph, toy_repo / "dvc.yaml")
    assert {stage: [path.as_posix() for path in files] for stage, files in missing.items()} == {
        "first": ["pipeline/helper.py", "src/carp/__init__.py", "src/carp/pkg/__init__.py", "src/carp/pkg/light.py"]
    }  # the second stage lists the whole library folder
    tool.write_code_deps(graph, toy_repo / "dvc.yaml")
    assert tool.missing_deps(graph, toy_repo / "dvc.yaml") == {}
    text = (toy_repo / "dvc.yaml").read_text()
    # A folder is listed whole only when the stage reaches all of it (pkg/heavy.py is not reached from stage.py).
    assert (
        "      - data/raw\n      # the script\n      - pipeline/stage.py\n      - pipeline/helper.py\n"
        "      - src/carp/__init__.py\n      - src/carp/base.py\n      - src/carp/pkg/__init__.py\n"
        "      - src/carp/pkg/light.py\n    outs:\n" in text
    )
    assert text.endswith(
        "        - pipeline/other.py\n        - src/carp/__init__.py\n        - src/carp/base.py\n"
        "        - src/carp/pkg\n        - src/carp/table.py\n        - src/carp/user.py\n"
    )


def test_circles_and_upward_imports_are_found(toy_repo):
    graph = tool.ImportGraph.build(toy_repo).library_graph()
    # table -> (string) pkg.heavy -> (lazy) user -> table
    assert tool.cycles(graph) == [["carp.pkg.heavy", "carp.table", "carp.user"]]
    assert ("carp.pkg.light", "carp.base") in graph.edges
    assert ("carp.pkg.light", "carp.pkg") not in graph.edges  # a package's own init is not an import of its module


def test_layers_name_every_library_module(repo_graph):
    graph = repo_graph.library_graph()
    for module in graph.nodes:
        tool.layer_of(module)  # raises for a module outside every layer
    with pytest.raises(ValueError, match="belongs to no layer"):
        tool.layer_of("elsewhere.module")


def test_the_library_has_no_import_circle_and_no_import_up_a_layer(repo_graph):
    graph = repo_graph.library_graph()
    assert tool.cycles(graph) == []
    assert tool.upward_imports(graph) == []
