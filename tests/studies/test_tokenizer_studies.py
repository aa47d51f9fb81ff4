"""The tokenizer studies on simulated experiments: kinds as points (a family that cannot take a kind skipped there),
the report's rate and distortion columns and verdicts against carp_msvq, the reuse study's source experiment and two
arms with their equivalence verdict, resumption, and the config's refusals."""

import json

import numpy as np
import pandas as pd
import pytest
import torch

from carp.config.checks import ConfigError
from carp.config.experiments import StudyConfig
from carp.config.tokenizer_kinds import BinningConfig
from carp.studies.setting_study import is_complete, load_study, run_points, study_sections
from carp.studies.tokenizer_studies import (
    REUSE_ALIAS,
    family_takes_kind,
    reuse_marker,
    reuse_study,
    run_source,
    tokenizer_study,
)
from carp.tokenizer.kinds.registry import build_tokenizer

KINDS = ("carp_msvq", "fast", "fsq")
EPISODES = 300
TAKES = family_takes_kind({"carp": ("carp_msvq",), "next_token": KINDS, "diffusion_unet": None}.get)
# Success by kind and family; fsq's coarse rate costs the next-token policy dearly.
RATE = {("carp_msvq", "carp"): 0.8, ("carp_msvq", "next_token"): 0.7, ("fast", "next_token"): 0.7,
        ("fsq", "next_token"): 0.2, ("pipeline", "carp"): 0.8, ("reused", "carp"): 0.8}  # fmt: skip
METRICS = {
    "carp_msvq": {"rmse_percent_range/mean": 1.0, "usage/all_scales/mean": 0.5},
    "fast": {"rmse_percent_range/mean": 0.5, "bits_per_chunk": 301.0, "tokens_per_chunk/mean": 30.1,
             "entropy_bits_per_chunk": 240.0},
    "fsq": {"rmse_percent_range/mean": 4.0, "bits_per_chunk": 32.6, "tokens_per_chunk/mean": 4.0,
            "entropy_bits_per_chunk": 30.0},
}  # fmt: skip


class FakePipeline:
    """Stands in for `dvc exp run`: writes what the evaluate and train_tokenizer stages would for the overrides."""

    def __init__(self, root, tasks=("square",), policies=("carp", "next_token"), seeds=(0, 1, 2), fail_at=None):
        self.root, self.tasks, self.policies, self.seeds, self.fail_at = root, tasks, policies, seeds, fail_at
        self.calls = []

    @property
    def eval_dir(self):
        return self.root / "eval"

    @property
    def metrics(self):
        return self.root / "tokenizer/metrics.json"

    def __call__(self, name, overrides):
        self.calls.append((name, overrides))
        if name == self.fail_at:
            raise RuntimeError(f"experiment {name} failed")
        settings = dict(override.split("=", 1) for override in overrides)
        policies = settings.get("policies", "[" + ",".join(self.policies) + "]").strip("[]").split(",")
        point = settings.get("tokenizer.kind") or (
            "pipeline" if settings["tokenizer.source"] == "pipeline" else "reused"
        )
        tasks = settings.get("tasks", "[" + ",".join(self.tasks) + "]").strip("[]").split(",")
        states = np.random.default_rng(7).random(EPISODES)
        for task in tasks:
            for family in policies:
                for seed in self.seeds:
                    self._evaluate(task, family, seed, RATE[(point, family)], states, point, family == "next_token")
        self.metrics.parent.mkdir(parents=True, exist_ok=True)
        self.metrics.write_text(json.dumps(METRICS.get(point, {"rmse_percent_range/mean": 2.0})))

    def _evaluate(self, task, family, seed, rate, states, point, repairs):
        generator = np.random.default_rng([seed, len(point), len(family)])
        # The reuse arms share most episodes' outcomes: the reused tokenizer changes little.
        shared = 0.97 if point in ("pipeline", "reused") else 0.3
        latent = np.where(generator.random(EPISODES) < shared, states, generator.random(EPISODES))
        success = latent < rate + 0.05 * np.random.default_rng(seed).standard_normal()
        summary = {"successes": int(success.sum()), "episodes": EPISODES, "latency_predict_ms_median": 3.0}
        summary["num_parameters"] = 1_000_000 + 1000 * len(point) + (0 if family == "carp" else 7)
        if repairs:
            summary.update(repaired_chunks=2 if point == "fast" else 0, predicted_chunks=100)
        path = self.eval_dir / task / family / f"seed{seed}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(summary))
        pd.DataFrame(
            {"seed": 100_000 + np.arange(EPISODES), "success": success, "steps": np.where(success, 90, 400)}
        ).to_csv(path.with_name(f"seed{seed}_episodes.csv"), index=False)


LISTS = {"policies": ["carp", "next_token"], "register": ["carp", "next_token"], "multitask": []}
MARKER = {"tasks": ["square"], "policies": ["carp", "next_token"], "seeds": [0, 1, 2]}


def run(fake, study, output, marker=MARKER):
    return run_points(study, marker, fake.eval_dir, fake.metrics, output, fake)


def test_each_kind_runs_once_resumes_and_a_family_that_cannot_take_it_is_left_out(tmp_path):
    study = tokenizer_study(KINDS, LISTS, TAKES)
    output = tmp_path / "study"
    failing = FakePipeline(tmp_path, fail_at="tokenizers-fsq")
    with pytest.raises(RuntimeError, match="tokenizers-fsq failed"):
        run(failing, study, output)
    assert failing.calls[0] == ("tokenizers-carp_msvq", ["tokenizer.kind=carp_msvq"])
    # carp predicts carp_msvq's tokens only: the fast point trains, evaluates and registers next_token alone.
    assert failing.calls[1] == (
        "tokenizers-fast",
        ["tokenizer.kind=fast", "policies=[next_token]", "register=[next_token]"],
    )
    assert sorted(p.name for p in (output / "fast/eval/square").iterdir()) == ["next_token"]
    assert is_complete(output / "fast", study.point_marker("fast", MARKER), "fast")
    again = FakePipeline(tmp_path)
    assert run(again, study, output) == ["fsq"]
    assert [name for name, _ in again.calls] == ["tokenizers-fsq"]


def test_a_family_without_tokens_trains_at_carp_msvq_only_and_a_kind_nobody_takes_is_refused():
    lists = {"policies": ["diffusion_unet", "next_token"], "register": [], "multitask": ["next_token", "carp"]}
    study = tokenizer_study(KINDS, lists, TAKES)
    assert study.families("carp_msvq", lists["policies"]) == ["diffusion_unet", "next_token"]
    assert study.overrides("fsq") == ["tokenizer.kind=fsq", "policies=[next_token]", "multitask=[next_token]"]
    with pytest.raises(ValueError, match="tokenizer kind fast: no family of policies=\\['carp'\\]"):
        tokenizer_study(KINDS, {"policies": ["carp"]}, TAKES)


def test_the_report_shows_rate_distortion_and_each_kind_against_carp_msvq_under_the_same_policy(tmp_path):
    study = tokenizer_study(KINDS, LISTS, TAKES)
    output = tmp_path / "study"
    run(FakePipeline(tmp_path), study, output)
    section = study_sections(study, load_study(study, [output], ["square"]), 0.05, 0.05, tmp_path / "figures")[0]
    table = section.tables[0].set_index(["point", "policy"])
    assert list(table.columns[-9:]) == [
        "tokenizer error (% of range)", "bits per chunk", "tokens per chunk", "entropy (bits per chunk)",
        "repaired chunks", "parameters", "demos replayed through the tokenizer", "latency per chunk (ms)",
        "against carp_msvq",
    ]  # fmt: skip
    assert list(table.index) == [("carp_msvq", "carp"), ("carp_msvq", "next_token"), ("fast", "next_token"),
                                 ("fsq", "next_token")]  # fmt: skip
    against = table["against carp_msvq"]
    assert against[("carp_msvq", "carp")] == against[("carp_msvq", "next_token")] == "reference"
    assert against[("fsq", "next_token")] == "next_token carp_msvq better"
    assert table.loc[("fast", "next_token"), "bits per chunk"] == "301"
    assert table.loc[("fast", "next_token"), "repaired chunks"] == "2.0%"
    assert table.loc[("carp_msvq", "carp"), "repaired chunks"] == "-"
    assert table.loc[("fast", "next_token"), "parameters"] == "1,004,007"
    assert table.loc[("carp_msvq", "carp"), "parameters"] == "1,009,000"
    assert table.loc[("fsq", "next_token"), "tokenizer error (% of range)"] == "4.00"
    assert (tmp_path / "figures" / "tokenizers_square.png").exists()


def test_carp_msvq_rate_is_read_from_its_tokenizer_copy(tmp_path):
    study = tokenizer_study(KINDS[:2], {"policies": ["next_token"]}, TAKES)
    output = tmp_path / "study"
    fake = FakePipeline(tmp_path, policies=("next_token",))
    tokenizer = build_tokenizer("binning", BinningConfig(bins=16), action_dim=2, action_horizon=4)
    tokenizer.fit(torch.rand(32, 4, 2))

    def experiment(name, overrides):  # each experiment leaves its tokenizer in the workspace
        fake(name, overrides)
        tokenizer.save(tmp_path / "models/tokenizer")

    marker = {**MARKER, "policies": ["next_token"]}
    run_points(study, marker, fake.eval_dir, fake.metrics, output, experiment, tmp_path / "models/tokenizer")
    table = study_sections(study, load_study(study, [output], ["square"]), 0.05, 0.05, tmp_path / "f")[0].tables[0]
    # 8 tokens of a 16-word vocabulary; the fast point's measured rate stays its own.
    assert table["bits per chunk"].tolist() == ["32", "301"]
    assert table["tokens per chunk"].tolist() == ["8.0", "30.1"]


def test_the_reuse_study_trains_the_source_once_and_gives_each_target_task_two_arms_and_a_verdict(tmp_path):
    targets, sources = ["nut_assembly", "threading"], ["lift", "can"]
    output = tmp_path / "reuse"
    fake = FakePipeline(tmp_path, tasks=targets, policies=("carp",), seeds=(0, 1, 2, 3, 4, 5))
    ref = tmp_path / "models/tokenizer_ref.json"

    def source(name, overrides):
        fake.calls.append((name, overrides))
        fake.metrics.parent.mkdir(parents=True, exist_ok=True)
        fake.metrics.write_text(json.dumps({"rmse_percent_range/mean": 0.8}))
        ref.parent.mkdir(parents=True, exist_ok=True)
        ref.write_text(json.dumps({"uri": f"models:/carp-tokenizer-panda@{REUSE_ALIAS}", "version": 3}))

    folders = (fake.metrics, tmp_path / "models/tokenizer", ref)
    assert run_source(sources, output, source, *folders)
    assert fake.calls == [("tokenizer_reuse-source", ["tasks=[lift,can]", "tokenizer.tasks=[lift,can]",
                           "tokenizer.source=pipeline", f"tokenizer.registry_alias={REUSE_ALIAS}"])]  # fmt: skip
    assert not run_source(sources, output, source, *folders)  # finished: not trained again
    assert run_source(["lift"], output, source, *folders)  # other source tasks: another tokenizer
    uri = f"models:/carp-tokenizer-panda@{REUSE_ALIAS}"
    study = reuse_study(targets, ["lift"], uri, {"rmse_percent_range/mean": 0.8})
    marker = reuse_marker({"tasks": ["lift"], "policies": ["carp"], "seeds": list(fake.seeds)}, targets, ["lift"])
    fake.calls.clear()
    fake.fail_at = "tokenizer_reuse-reused"
    with pytest.raises(RuntimeError):
        run(fake, study, output, marker)
    assert fake.calls[0] == ("tokenizer_reuse-own", ["tokenizer.source=pipeline", "tasks=[nut_assembly,threading]",
                             "tokenizer.tasks=[nut_assembly,threading]"])  # fmt: skip
    assert fake.calls[1][1][0] == f"tokenizer.source={uri}"
    fake.fail_at = None
    assert run(fake, study, output, marker) == [uri]
    sections = study_sections(study, load_study(study, [output], targets), 0.05, 0.05, tmp_path / "figures")
    assert [section.title for section in sections] == [
        "Tokenizer reuse study on nut_assembly", "Tokenizer reuse study on threading"
    ]  # fmt: skip
    table = sections[0].tables[0]
    assert table["point"].tolist() == ["own tokenizer", "reused tokenizer"]
    assert table["against own tokenizer"].tolist() == ["reference", "on par within ±5 points"]
    assert any("trained on lift, 0.80% of range" in paragraph for paragraph in sections[0].paragraphs)


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"tokenizer_kinds": ("fast", "fsq")}, "study.tokenizer_kinds=['fast', 'fsq']: must hold at least two"),
        ({"tokenizer_kinds": ("carp_msvq", "vq")}, "study.tokenizer_kinds=['carp_msvq', 'vq']: every kind must be"),
        ({"reuse_target_tasks": ()}, "study.reuse_target_tasks=[]: must hold at least one task"),
        ({"reuse_target_tasks": ("stack", "threading")}, "must not hold a source task (stack)"),
    ],
)
def test_the_config_refuses_bad_study_settings_in_one_line(settings, message):
    with pytest.raises(ConfigError) as raised:
        StudyConfig(**settings)
    assert message in str(raised.value) and "\n" not in str(raised.value)
