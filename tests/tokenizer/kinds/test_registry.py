"""The kind table: its names, its refusals, and the params sections that name the same kinds."""

import pytest

from carp.config import Params, params_from_dict
from carp.config.checks import ConfigError
from carp.config.tokenizer import TokenizerConfig
from carp.config.tokenizer_kinds import (
    TOKENIZER_KINDS,
    BinningConfig,
    BSplineConfig,
    FastConfig,
    FsqConfig,
    JointMsvqConfig,
    ResidualVqConfig,
    kind_section,
)
from carp.tokenizer.kinds.registry import build_tokenizer, kind_class, kind_names, load_tokenizer
from tests.tokenizer.kinds.conftest import A, H


def test_the_params_and_the_registry_name_the_same_kinds_default_first():
    assert kind_names() == TOKENIZER_KINDS
    assert kind_names()[0] == "carp_msvq" == TokenizerConfig().kind


def test_every_kind_is_a_class_named_after_it():
    for kind in kind_names():
        assert kind_class(kind).kind == kind


def test_an_unknown_kind_is_refused_naming_the_known_ones():
    known = "carp_msvq, binning, fast, bspline, fsq, joint_msvq, residual_vq"
    with pytest.raises(KeyError, match=rf"unknown tokenizer kind 'vq' \(known: {known}\)"):
        kind_class("vq")


def test_the_params_refuse_an_unknown_kind_in_one_line_naming_the_key_and_the_kinds():
    with pytest.raises(ConfigError) as raised:
        TokenizerConfig(kind="vq")
    message = str(raised.value)
    assert message == (
        "tokenizer.kind='vq': must be one of carp_msvq, binning, fast, bspline, fsq, joint_msvq, residual_vq"
    )
    assert "\n" not in message


@pytest.mark.parametrize(
    ("section", "message"),
    [
        (lambda: BinningConfig(bins=1), r"tokenizer_binning.bins=1: must be an integer >= 2"),
        (
            lambda: BinningConfig(lower_percentile=60.0),
            r"tokenizer_binning.lower_percentile=60.0: must be in \[0, 50\)",
        ),
        (lambda: FastConfig(scale=0.0), r"tokenizer_fast.scale=0.0: must be > 0"),
        (lambda: BSplineConfig(control_points=3), r"tokenizer_bspline.control_points=3: must be an integer >= degree"),
        (lambda: FsqConfig(levels=(8, 1)), r"tokenizer_fsq.levels=\[8, 1\]: must be a non-empty list of integers >= 2"),
        (lambda: FsqConfig(downsampling=3), r"tokenizer_fsq.downsampling=3: must be a power of two"),
        (lambda: JointMsvqConfig(scales=(2, 1)), r"tokenizer_joint_msvq.scales=\[2, 1\]: must be strictly increasing"),
        (lambda: JointMsvqConfig(downsampling=1), r"tokenizer_joint_msvq.downsampling=1: must be a power of two >= 2"),
        (lambda: ResidualVqConfig(num_codes=1), r"tokenizer_residual_vq.num_codes=1: must be an integer >= 2"),
        (lambda: ResidualVqConfig(num_layers=0), r"tokenizer_residual_vq.num_layers=0: must be an integer >= 1"),
        (lambda: ResidualVqConfig(codebook_decay=1.0), r"tokenizer_residual_vq.codebook_decay=1.0: must be in \(0, 1"),
    ],
)
def test_each_kinds_section_refuses_bad_settings_naming_the_key(section, message):
    with pytest.raises(ConfigError, match=message):
        section()


@pytest.mark.parametrize(
    ("kind", "section", "message"),
    [
        ("bspline", {"control_points": 17}, "tokenizer_bspline.control_points=17: must be at most H = 16"),
        ("fsq", {"downsampling": 32}, "tokenizer_fsq.downsampling=32: must divide H = 16"),
        ("joint_msvq", {"downsampling": 32}, "tokenizer_joint_msvq.downsampling=32: must divide H = 16"),
    ],
)
def test_the_selected_kinds_length_settings_are_checked_against_the_horizon_in_one_line(kind, section, message):
    raw = {"tokenizer": {"kind": kind}, "policies": ["next_token"], kind_section(kind): section}
    with pytest.raises(ConfigError) as raised:
        params_from_dict(raw)
    assert str(raised.value) == message.replace("H = ", "data.action_horizon = ")
    # The same settings stand while another kind is selected: only the selected kind's tokens depend on them.
    params_from_dict({**raw, "tokenizer": {"kind": "binning"}})


@pytest.mark.parametrize("kind", ["binning", "fast", "bspline", "fsq", "joint_msvq", "residual_vq"])
def test_each_kind_builds_from_its_default_section(kind):
    tokenizer = build_tokenizer(kind, getattr(Params(), kind_section(kind)), A, H)
    assert (tokenizer.kind, tokenizer.action_dim, tokenizer.action_horizon) == (kind, A, H)


def test_carp_msvq_is_not_built_from_a_section():
    with pytest.raises(ValueError, match="'carp_msvq' is not built from a params section"):
        build_tokenizer("carp_msvq", None, A, H)


def test_a_folder_without_a_tokenizer_is_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match="kind.json: no tokenizer kind file"):
        load_tokenizer(tmp_path)
