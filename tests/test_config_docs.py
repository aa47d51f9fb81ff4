import dataclasses
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import yaml

from carp.config import Params
from carp.config_docs import config_sections, documentation_problems, field_descriptions, params_reference

REPO = Path(__file__).resolve().parents[1]


def test_every_field_of_every_config_section_is_documented():
    sections = config_sections()
    assert [prefix for prefix, _ in sections] == [
        "",
        "data.",
        "tokenizer.",
        "tokenizer_carp_msvq.",
        "tokenizer_binning.",
        "tokenizer_fast.",
        "tokenizer_bspline.",
        "tokenizer_fsq.",
        "tokenizer_joint_msvq.",
        "tokenizer_residual_vq.",
        "training.",
        "eval.",
        "tracking.",
        "sweep.",
        "comparison.",
        "study.",
        "serving.",
        "image_encoder.",
        "carp.",
        "inference.carp.",
        "diffusion_unet.",
        "inference.diffusion_unet.",
        "diffusion_transformer.",
        "inference.diffusion_transformer.",
        "next_token.",
        "inference.next_token.",
        "vq_bet.",
        "inference.vq_bet.",
        "edm_unet.",
        "inference.edm_unet.",
        "consistency_policy.",
        "inference.consistency_policy.",
    ]
    assert documentation_problems() == []
    for _, cls in sections:
        descriptions = field_descriptions(cls)
        for config_field in dataclasses.fields(cls):
            if dataclasses.is_dataclass(config_field.type):
                continue  # a section: its own fields carry the details
            # Meaning plus at least its range or constraint: more than a few words.
            assert len(descriptions[config_field.name].split()) >= 6, (cls.__name__, config_field.name)


def test_the_committed_params_page_is_what_the_docstrings_generate():
    committed = (REPO / "docs" / "params.md").read_text()
    assert committed == params_reference(), "docs/params.md is out of date: run `make docs`"


def test_the_page_lists_every_key_of_params_yaml_with_its_default():
    page = params_reference()
    raw = yaml.safe_load((REPO / "params.yaml").read_text())

    def keys(mapping, prefix=""):
        for key, value in mapping.items():
            sections = {p for p, _ in config_sections()}
            if isinstance(value, dict) and any(p.startswith(f"{prefix}{key}.") for p in sections):
                yield from keys(value, f"{prefix}{key}.")
            else:
                yield f"{prefix}{key}"

    for key in keys(raw):
        assert f"- `{key}` (" in page, key
    assert "- `inference.carp.top_k` (integer, default `1`):" in page
    assert "- `carp.depth` (integer, default `8`):" in page
    assert "- `data.filter_key` (string or null, default `null`):" in page
    assert (
        "- `sweep.scale_schedules` (list of lists of integers, default `[[4], [1, 4], [1, 2, 4], [1, 2, 3, 4]]`)"
        in page
    )
    assert "``" not in page


@dataclass(frozen=True)
class _Section:
    """A section.

    Attributes:
        documented: A value with a description that
            continues on a second line.
        stale: Describes a field that no longer exists.
    """

    documented: int = 1
    undocumented: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class _Root:
    """The root.

    Attributes:
        section: The only section.
    """

    section: _Section = field(default_factory=_Section)


def test_an_undocumented_or_stale_field_is_reported_by_key():
    assert field_descriptions(_Section)["documented"] == "A value with a description that continues on a second line."
    assert documentation_problems(_Root) == [
        "section.undocumented: no description in _Section's docstring",
        "section.stale: described in _Section's docstring but not a field of it",
    ]
    with pytest.raises(ValueError, match="section.undocumented"):
        params_reference(_Root)


def test_params_docs_check_fails_on_an_out_of_date_page(tmp_path):
    script = REPO / "tools" / "params_docs.py"
    current = subprocess.run([sys.executable, script, "--check"], capture_output=True, text=True, cwd=REPO)
    assert current.returncode == 0, current.stderr
    # A copy of the tool whose page is a stale file: the check names the page and the command that fixes it.
    stale_page = tmp_path / "docs" / "params.md"
    stale_page.parent.mkdir()
    stale_page.write_text("# Parameters\n")
    copy = tmp_path / "tools" / "params_docs.py"
    copy.parent.mkdir()
    copy.write_text(script.read_text())
    stale = subprocess.run([sys.executable, copy, "--check"], capture_output=True, text=True, cwd=tmp_path)
    assert stale.returncode == 1
    assert stale.stderr.strip() == f"error: {stale_page}: out of date with src/carp/config.py; run `make docs`"
    assert stale_page.read_text() == "# Parameters\n"


def test_params_defaults_render_as_yaml():
    assert "- `eval.max_steps` (mapping of task to integer, default `{lift: 400, can: 400, square: 400}`)" in (
        params_reference(Params)
    )


@dataclass(frozen=True)
class _Base:
    """A base section.

    Attributes:
        shared: Documented once, here.
        changed: The base's description.
    """

    shared: int = 1
    changed: int = 2


@dataclass(frozen=True)
class _Derived(_Base):
    """A section that adds one field and redescribes another.

    Attributes:
        changed: The subclass's description.
        added: A field of the subclass.
    """

    added: int = 3


def test_a_subclass_inherits_its_bases_descriptions_and_may_replace_them():
    assert field_descriptions(_Derived) == {
        "shared": "Documented once, here.",
        "changed": "The subclass's description.",
        "added": "A field of the subclass.",
    }
    assert documentation_problems(_Derived) == []
