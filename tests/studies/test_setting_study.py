"""The scales and codebook studies on simulated experiments: points run once, resume, join across folders, and the
report's verdicts against the reference point and its check of the paper's Fig. 10."""

import json

import numpy as np
import pandas as pd
import pytest

from carp.studies.setting_study import (
    codebook_study,
    is_complete,
    load_study,
    run_points,
    scales_study,
    study_sections,
    write_study_report,
)

SCHEDULES = ((1,), (1, 2), (1, 2, 3), (1, 2, 3, 4), (1, 2, 3, 4, 5))
MARKER = {"tasks": ["square"], "policies": ["carp"], "seeds": [0, 1, 2]}
EPISODES = 300
# Success by number of scales: coarse schedules much worse, K = 5 as good as K = 4.
RATE_BY_K = {1: 0.3, 2: 0.45, 3: 0.6, 4: 0.85, 5: 0.85}


class FakeExperiments:
    """Stands in for `dvc exp run`: writes each seed's evaluation and the tokenizer's metrics as the stages would."""

    def __init__(self, eval_dir, tokenizer_metrics, seeds=(0, 1, 2), fail_at=None):
        self.eval_dir, self.tokenizer_metrics, self.seeds, self.fail_at = eval_dir, tokenizer_metrics, seeds, fail_at
        self.calls = []

    def __call__(self, name, overrides):
        self.calls.append((name, overrides))
        if name == self.fail_at:
            raise RuntimeError(f"experiment {name} failed")
        schedule = json.loads(overrides[0].split("=", 1)[1])
        rate = RATE_BY_K[len(schedule)]
        states = np.random.default_rng(7).random(EPISODES)  # shared state difficulty
        for seed in self.seeds:
            generator = np.random.default_rng([len(schedule), seed])
            latent = np.where(generator.random(EPISODES) < 0.3, states, generator.random(EPISODES))
            success = latent < rate
            summary = self.eval_dir / "square" / "carp" / f"seed{seed}.json"
            summary.parent.mkdir(parents=True, exist_ok=True)
            summary.write_text(
                json.dumps({"successes": int(success.sum()), "episodes": EPISODES, "latency_predict_ms_median": 3.0})
            )
            pd.DataFrame(
                {"seed": 100_000 + np.arange(EPISODES), "success": success, "steps": np.where(success, 90, 400)}
            ).to_csv(summary.with_name(f"seed{seed}_episodes.csv"), index=False)
        self.tokenizer_metrics.parent.mkdir(parents=True, exist_ok=True)
        error = 3.0 / len(schedule)
        self.tokenizer_metrics.write_text(
            json.dumps({"rmse_percent_range/mean": error, "usage/all_scales/mean": 0.5, "perplexity/mean": 100.0})
        )


def run(tmp_path, study, fake, output):
    return run_points(study, MARKER, tmp_path / "eval", tmp_path / "tokenizer/metrics.json", output, fake)


def test_each_point_runs_once_and_an_interrupted_study_resumes(tmp_path):
    study = scales_study(SCHEDULES, (1, 2, 3, 4))
    output = tmp_path / "study"
    failing = FakeExperiments(tmp_path / "eval", tmp_path / "tokenizer/metrics.json", fail_at="scales-K3")
    with pytest.raises(RuntimeError, match="scales-K3 failed"):
        run(tmp_path, study, failing, output)
    assert [name for name, _ in failing.calls] == ["scales-K1", "scales-K2", "scales-K3"]
    assert failing.calls[1][1] == ["scales=[1,2]"]
    assert is_complete(output / "K2", MARKER, (1, 2)) and not (output / "K3").exists()
    again = FakeExperiments(tmp_path / "eval", tmp_path / "tokenizer/metrics.json")
    assert run(tmp_path, study, again, output) == [(1, 2, 3), (1, 2, 3, 4), (1, 2, 3, 4, 5)]
    assert [name for name, _ in again.calls] == ["scales-K3", "scales-K4", "scales-K5"]
    # Another layout (other seeds) is another study: nothing counts as complete.
    assert not is_complete(output / "K2", {**MARKER, "seeds": [0]}, (1, 2))


def test_the_report_compares_every_point_with_the_reference_and_checks_the_papers_reading(tmp_path):
    study = scales_study(SCHEDULES, (1, 2, 3, 4))
    output = tmp_path / "study"
    run(tmp_path, study, FakeExperiments(tmp_path / "eval", tmp_path / "tokenizer/metrics.json"), output)
    points = load_study(study, [output], ["square"])
    section = study_sections(study, points, margin=0.05, alpha=0.05, figures_dir=tmp_path / "figures")[0]
    table = section.tables[0]
    assert table["point"].tolist() == [study.label(schedule) for schedule in SCHEDULES]
    assert table.loc[table["point"] == "K=4 [1, 2, 3, 4]", "against K=4 [1, 2, 3, 4]"].item() == "reference"
    assert table.loc[table["point"] == "K=1 [1]", "against K=4 [1, 2, 3, 4]"].item() == "carp K=4 [1, 2, 3, 4] better"
    assert table["tokenizer error (% of range)"].tolist() == ["3.00", "1.50", "1.00", "0.75", "0.60"]
    claims = section.tables[1].set_index("claim")["verdict"]
    assert claims["fewer than 4 scales tokenize too coarsely (worse than 4)"] == "holds"
    # K = 5 against K = 4 at the same rate: 3 seeds of 300 episodes cannot show "within 5 points".
    assert claims["5 and 6 scales add nothing (on par with 4)"] == "not decided"
    markdown = write_study_report(study, points, 0.05, 0.05, output).read_text()
    assert "## Scales study on square" in markdown and (output / "figures" / "scales_square.png").exists()


def test_a_study_split_over_folders_is_reported_as_one_and_one_seed_decides_nothing(tmp_path):
    study = codebook_study((64, 512), 512)
    here, there = tmp_path / "here", tmp_path / "there"
    marker_one = {**MARKER, "seeds": [0]}

    class Codebook(FakeExperiments):
        def __call__(self, name, overrides):
            size = int(overrides[0].split("=")[1])
            return super().__call__(name, [f"scales=[{','.join(map(str, range(1, 2 if size == 64 else 5)))}]"])

    run_points(study, marker_one, tmp_path / "a", tmp_path / "a/metrics.json", here, Codebook(
        tmp_path / "a", tmp_path / "a/metrics.json", seeds=(0,)))  # fmt: skip
    points = load_study(study, [here], ["square"])
    alone = study_sections(study, points, 0.05, 0.05, tmp_path / "f1")[0].tables[0]
    assert alone.loc[alone["point"] == "V=64", "against V=512"].item() == "not decided (1 training seed)"
    marker_two = {**MARKER, "seeds": [1, 2]}
    run_points(study, marker_two, tmp_path / "b", tmp_path / "b/metrics.json", there, Codebook(
        tmp_path / "b", tmp_path / "b/metrics.json", seeds=(1, 2)))  # fmt: skip
    joined = study_sections(study, load_study(study, [here, there], ["square"]), 0.05, 0.05, tmp_path / "f2")
    table = joined[0].tables[0]
    assert table["seeds"].tolist() == [3, 3]
    assert table.loc[table["point"] == "V=64", "against V=512"].item() == "carp V=512 better"


def test_a_reference_outside_the_points_is_refused():
    with pytest.raises(ValueError, match="reference"):
        codebook_study((64, 256), 512)


def test_each_point_keeps_its_tokenizer_and_its_replay_shows_in_the_report(tmp_path):
    study = scales_study(SCHEDULES[2:4], (1, 2, 3, 4))
    output, tokenizer = tmp_path / "study", tmp_path / "models/tokenizer"
    fake = FakeExperiments(tmp_path / "eval", tmp_path / "tokenizer/metrics.json")
    replayed = []

    def experiment(name, overrides):  # each experiment leaves its own tokenizer in the workspace
        fake(name, overrides)
        tokenizer.mkdir(parents=True, exist_ok=True)
        (tokenizer / "tokenizer.json").write_text(json.dumps({"scales": overrides[0]}))

    def replay(point_dir):  # stands in for `point_replay.replay_point`: one demo fewer per missing scale
        replayed.append(point_dir.name)
        kept = json.loads((point_dir / "tokenizer" / "tokenizer.json").read_text())["scales"]
        k = len(json.loads(kept.split("=", 1)[1]))
        (point_dir / "replay.json").write_text(json.dumps({"square": {"successes": 46 + k, "demos": 50}}))

    run_points(study, MARKER, tmp_path / "eval", tmp_path / "tokenizer/metrics.json", output, experiment, tokenizer,
               replay)  # fmt: skip
    assert json.loads((output / "K3/tokenizer/tokenizer.json").read_text()) == {"scales": "scales=[1,2,3]"}
    # A finished study run again measures each point's replay again only through `replay` (which skips stored ones).
    assert run_points(study, MARKER, tmp_path / "eval", tmp_path / "tokenizer/metrics.json", output, experiment,
                      tokenizer, replay) == []  # fmt: skip
    assert replayed == ["K3", "K4", "K3", "K4"]
    table = study_sections(study, load_study(study, [output], ["square"]), 0.05, 0.05, tmp_path / "figures")[0]
    assert table.tables[0]["demos replayed through the tokenizer"].tolist() == ["49/50", "50/50"]
