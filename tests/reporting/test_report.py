import base64
import dataclasses
import re

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
import pytest

from carp.evaluation.metrics import summarize_episodes
from carp.evaluation.rollout import EpisodeResult
from carp.evaluation.runner import write_episode_videos
from carp.reporting.comparison import compare_multitask, seed_table
from carp.reporting.report import ReportInputs, write_report
from carp.reporting.report_tables import (
    comparison_table,
    inference_budget_lines,
    latency_table,
    multitask_table,
    success_table,
)
from carp.reporting.runs import RunResults, pooled_metrics


@pytest.fixture
def inputs(tmp_path):
    figure = tmp_path / "reconstruction.png"
    plt.plot([0, 1], [1, 0])
    plt.savefig(figure)
    plt.close()
    lift = summarize_episodes(
        successes=[True] * 45 + [False] * 5,
        steps=[120] * 50,
        crashed=[False] * 49 + [True],
        prediction_seconds=[0.002] * 10,
        decoding_seconds=[0.0005] * 10,
    )
    lift.update(
        {
            "batched_latency_batch_size": 64,
            "batched_latency_predict_ms_median": 9.0,
            "batched_latency_predict_ms_p90": 10.0,
            "batched_latency_decode_ms_median": 1.0,
            "batched_latency_decode_ms_p90": 1.5,
            "top_k": 1,
        }
    )
    history = pd.DataFrame(
        {
            "epoch": [1, 2, 3],
            "loss": [3.0, 2.0, 1.0],
            "token_accuracy_scale_1": [0.2, 0.5, 0.9],
            "epoch_seconds": [40.0, 40.0, 40.0],
        }
    )
    return ReportInputs(
        evaluation={"lift": {"carp": lift | {"backend": "onnxruntime", "inference": "greedy", "action_steps": 8}}},
        tokenizer_metrics={
            "rmse/x": 0.001,
            "rmse/mean": 0.001,
            "rmse_percent_range/x": 0.75,
            "rmse_percent_range/mean": 0.75,
            "max_error/x": 0.004,
            "max_error/max": 0.004,
            "usage/all_scales/x": 0.5,
            "perplexity/x": 40.0,
        },
        tokenizer_history=pd.DataFrame({"epoch": [1, 2], "loss": [0.5, 0.1], "reconstruction_loss": [0.4, 0.05]}),
        policy_histories={"lift": {"carp": history}},
        reconstruction_figure=figure,
        sweep_trials=pd.DataFrame(
            {
                "num_scales": [2, 4, 2, 4],
                "codebook_size": [64, 64, 256, 256],
                "validation_success_rate": [0.5, 0.9, 0.6, 0.95],
            }
        ),
        versions={"robosuite": "1.5.2", "mujoco": "3.3.7", "torch": "2.13.0"},
        git_commit="abc123",
        params_yaml="scales: [1, 2, 3, 4]\n",
    )


def test_report_contains_every_section_and_numbers(tmp_path, inputs):
    markdown_path, html_path = write_report(inputs, tmp_path / "reports")
    markdown = markdown_path.read_text()
    for heading in (
        "Success rate",
        "Inference latency",
        "Action tokenizer",
        "Training curves",
        "Sweep over scales",
        "Provenance",
    ):
        assert f"## {heading}" in markdown
    assert "45/50" in markdown and "90.0%" in markdown and "78.6-95.7%" in markdown and "greedy" in markdown
    assert "2.00" in markdown and "B=64" in markdown
    assert "| x " in markdown and "0.75% of each dimension's range" in markdown
    assert "robosuite 1.5.2" in markdown and "abc123" in markdown and "scales: [1, 2, 3, 4]" in markdown
    for figure in re.findall(r"!\[[^]]*\]\(([^)]+)\)", markdown):
        assert (markdown_path.parent / figure).exists()
    assert (markdown_path.parent / "figures" / "sweep_scales.png").exists()


def test_a_tokenizer_shared_by_several_tasks_gets_a_row_per_task(tmp_path, inputs):
    per_task = {
        "task/can/rmse_percent_range/x": 0.5,
        "task/can/rmse_percent_range/y": 1.5,
        "task/can/rmse_percent_range/mean": 1.0,
        "task/can/max_error/max": 0.02,
        "task/stack/rmse_percent_range/x": 2.5,
        "task/stack/rmse_percent_range/y": 0.5,
        "task/stack/rmse_percent_range/mean": 1.5,
        "task/stack/max_error/max": 0.03,
    }
    shared = dataclasses.replace(inputs, tokenizer_metrics=inputs.tokenizer_metrics | per_task)
    section = write_report(shared, tmp_path / "shared")[0].read_text().split("## Action tokenizer", 1)[1]
    section = section.split("\n## ", 1)[0]
    rows = [
        [cell.strip() for cell in line.strip("|").split("|")]
        for line in section.splitlines()
        if line.startswith(("| can ", "| stack "))
    ]
    assert rows == [["can", "1", "y (1.5%)", "0.02"], ["stack", "1.5", "x (2.5%)", "0.03"]]
    alone = write_report(inputs, tmp_path / "alone")[0].read_text()
    assert "each task's held-out windows alone" not in alone


def test_camera_images_get_a_grid_per_task_only_when_a_run_has_them(tmp_path, inputs):
    assert "## Camera images" not in write_report(inputs, tmp_path / "state")[0].read_text()
    frames = {
        key: np.random.default_rng(0).integers(0, 256, (9, 12, 12, 3), dtype=np.uint8)
        for key in ("agentview_image", "robot0_eye_in_hand_image")
    }
    markdown_path, _ = write_report(dataclasses.replace(inputs, camera_frames={"lift": frames}), tmp_path / "image")
    markdown = markdown_path.read_text()
    assert "## Camera images" in markdown and "figures/cameras_lift.png" in markdown
    grid = plt.imread(markdown_path.parent / "figures" / "cameras_lift.png")
    assert grid.shape[0] > 100 and grid.shape[1] > grid.shape[0]  # six columns of frames, two rows


def test_rollout_videos_are_shown_as_animated_gifs_in_both_documents(tmp_path, inputs):
    assert "## Rollout videos" not in write_report(inputs, tmp_path / "none")[0].read_text()
    frames = [np.full((16, 16, 3), shade, dtype=np.uint8) for shade in (0, 90, 180, 250)]
    episode = EpisodeResult(seed=100000, success=True, steps=4, seconds=0.1, frames=frames)
    videos = write_episode_videos([episode], tmp_path / "eval" / "videos", "lift_carp")
    markdown_path, html_path = write_report(dataclasses.replace(inputs, videos={"lift": videos}), tmp_path / "out")
    assert "## Rollout videos" in markdown_path.read_text()
    assert "../eval/videos/lift_carp_seed100000.gif" in markdown_path.read_text()
    embedded = re.findall(r"src='data:image/gif;base64,([^']+)'", html_path.read_text())
    assert len(embedded) == 1 and base64.b64decode(embedded[0]) == videos[0].read_bytes()


def test_html_is_self_contained(tmp_path, inputs):
    _, html_path = write_report(inputs, tmp_path / "reports")
    page = html_path.read_text()
    assert "<script" not in page and "http://" not in page and "https://" not in page
    images = re.findall(r"src='data:image/png;base64,([^']+)'", page)
    assert len(images) >= 4
    assert base64.b64decode(images[0])[:4] == b"\x89PNG"
    assert "45/50" in page


def test_success_table_names_each_rows_token_choice(inputs):
    lift = inputs.evaluation["lift"]["carp"]
    legacy = {k: v for k, v in lift.items() if k not in ("top_k", "inference")}
    table = success_table(
        {"lift": {"carp": lift}, "can": {"carp": {**lift, "inference": None, "top_k": 5}}, "square": {"carp": legacy}}
    )
    assert table.set_index("task")["decoding"].to_dict() == {"lift": "greedy", "can": "top-5 draws", "square": "-"}


def test_success_table_shows_the_repaired_share_where_a_policy_reports_it(inputs):
    lift = inputs.evaluation["lift"]["carp"]
    assert "repaired chunks" not in success_table({"lift": {"carp": lift}}).columns
    fast = lift | {"repaired_chunks": 3, "predicted_chunks": 40, "repaired_chunk_rate": 0.075}
    table = success_table({"lift": {"carp": lift, "next_token": fast}}).set_index("policy")
    assert table["repaired chunks"].to_dict() == {"carp": "-", "next_token": "7.5%"}


def _baseline(lift: dict) -> dict:
    """The same episodes as a slower family with 10 denoising steps in PyTorch."""
    return lift | {
        "inference": "DDIM-10",
        "backend": "torch",
        "model_calls_per_chunk": 10,
        "num_parameters": 9_000_000,
        "latency_predict_ms_median": 40.0,
        "latency_predict_ms_p90": 45.0,
    }


def test_one_comparison_table_per_task_with_a_row_per_policy(tmp_path, inputs):
    lift = inputs.evaluation["lift"]["carp"]
    inputs.evaluation["lift"]["diffusion_transformer"] = _baseline(lift)
    table = comparison_table(inputs.evaluation["lift"], inputs.policy_histories["lift"]).set_index("policy")
    assert list(table.index) == ["carp", "diffusion_transformer"]
    assert table.loc["carp", "95% interval"] == "78.6-95.7%" and table.loc["carp", "training"] == "2.0 min"
    assert table.loc["carp", "predict ms (median / p90)"] == "2.00 / 2.00"
    assert table.loc["diffusion_transformer", "model calls"] == "10"
    assert table.loc["diffusion_transformer", "parameters"] == "9,000,000"
    assert (
        table.loc["diffusion_transformer", "backend"] == "torch"
        and table.loc["diffusion_transformer", "training"] == "-"
    )
    markdown = write_report(inputs, tmp_path / "reports")[0].read_text()
    assert "## Policies on lift" in markdown and "DDIM-10" in markdown
    assert (tmp_path / "reports" / "figures" / "success_vs_latency.png").exists()


def test_inference_budget_counts_the_chunks_of_the_tasks_episode_limit(inputs):
    lift = inputs.evaluation["lift"]["carp"]
    lines = inference_budget_lines({"lift": {"carp": lift, "diffusion_transformer": _baseline(lift)}})
    # 400 steps / Ta = 8 -> 50 chunks; 2.0 + 0.5 ms and 40.0 + 0.5 ms per chunk.
    assert (
        lines[0]
        == "lift, carp (greedy, onnxruntime): 0.12 s of inference over 400 control steps (50 chunks of 2.50 ms)"
    )
    assert lines[1].startswith("lift, diffusion_transformer (DDIM-10, torch): 2.02 s")
    # An image policy's cameras are rendered at every control step: that time comes apart from the policy's.
    # Push-T's episodes end at 300 steps: its budget is 300 / 8 -> 38 chunks.
    pusht = inference_budget_lines({"pusht": {"carp": lift}})
    assert pusht[0] == (
        "pusht, carp (greedy, onnxruntime): 0.10 s of inference over 300 control steps (38 chunks of 2.50 ms)"
    )
    seen = inference_budget_lines({"lift": {"carp": {**lift, "render_step_ms_median": 60.0}}})
    assert seen[0].endswith("(50 chunks of 2.50 ms); rendering the cameras: 24.00 s (60.00 ms per step)")
    with_encoder = {**lift, "render_step_ms_median": 60.0, "latency_encode_ms_median": 1.25}
    seen = inference_budget_lines({"lift": {"carp": with_encoder}})
    assert seen[0].endswith(
        "(50 chunks of 2.50 ms), 1.25 ms of each in the camera encoder; "
        "rendering the cameras: 24.00 s (60.00 ms per step)"
    )


def test_latency_table_gives_the_camera_encoders_share_for_image_policies_only(inputs):
    lift = inputs.evaluation["lift"]["carp"]
    image = {**lift, "latency_encode_ms_median": 1.25, "batched_latency_encode_ms_median": 9.5}
    table = latency_table({"lift": {"carp": lift}, "can": {"carp": image}})
    assert table.loc[table.task == "lift", "encoder median"].tolist() == ["-"] * 2
    assert table.loc[table.task == "can", "encoder median"].tolist() == ["1.25", "9.50"]


def _runs(rates_by_seed: dict[int, float], chunk_ms: float, flip: int = 0) -> dict:
    """One family's results over training seeds: 100 test episodes each at the given rate.

    Each training seed succeeds on its own shuffle of the states (the same shuffle for every family at that seed, so
    a family at a higher rate succeeds wherever one at a lower rate does). `flip` successes at the start and as many
    failures at the end of the shuffled order swap outcome: the same rate, other episodes.
    """
    runs = {}
    for seed, rate in rates_by_seed.items():
        ordered = np.arange(100) < round(100 * rate)
        ordered[:flip] = False
        ordered[100 - flip :] = True
        success = np.empty(100, bool)
        success[np.random.default_rng(seed).permutation(100)] = ordered
        episodes = pd.DataFrame(
            {
                "seed": 100_000 + np.arange(100),
                "success": success,
                "steps": np.where(success, 60 + np.arange(100) % 30, 400),
                "chunk_ms_median": chunk_ms + 0.01 * (np.arange(100) % 7),
            }
        )
        metrics = summarize_episodes(
            successes=success.tolist(),
            steps=episodes["steps"].tolist(),
            crashed=[False] * 100,
            prediction_seconds=[chunk_ms / 1000] * 10,
            decoding_seconds=[0.0] * 10,
        ) | {"selected_epoch": 40, "candidates": 4, "validation_max_success_rate": min(1.0, rate + 0.06)}
        metrics |= {"validation_top_k_mean_success_rate": rate + 0.03, "validation_top_k": 3}
        metrics["validation_max_test_gap"] = metrics["validation_max_success_rate"] - metrics["success_rate"]
        runs[seed] = RunResults(metrics, episodes)
    return runs


def test_comparison_sections_give_per_seed_rows_verdicts_and_the_papers_claims(tmp_path, inputs):
    # Five training seeds: on par within 5 points needs more than three at 100 episodes a seed.
    strong = {0: 0.95, 1: 0.93, 2: 0.96, 3: 0.94, 4: 0.95}
    runs = {
        "lift": {
            "carp": _runs(strong, chunk_ms=3.0),
            "diffusion_unet": _runs(strong, chunk_ms=45.0, flip=2),
            "next_token": _runs({0: 0.55, 1: 0.50, 2: 0.60, 3: 0.52, 4: 0.57}, chunk_ms=50.0),
        }
    }
    evaluation = {"lift": {family: pooled_metrics(seed_runs) for family, seed_runs in runs["lift"].items()}}
    assert (
        evaluation["lift"]["carp"]["successes"] == 95 + 93 + 96 + 94 + 95 and evaluation["lift"]["carp"]["seeds"] == 5
    )
    report = dataclasses.replace(inputs, evaluation=evaluation, runs=runs, max_steps={"lift": 400})
    markdown = write_report(report, tmp_path / "reports")[0].read_text()
    section = markdown.split("## Comparison on lift", 1)[1].split("\n## ", 1)[0]
    # A seed row per family and seed, with the selected checkpoint, validation max and the gap to the test success.
    assert (
        len(
            [line for line in section.splitlines() if line.startswith("| carp ") and "epoch 40 of 4 candidates" in line]
        )
        == 5
    )
    assert "| +6.0 points" in section
    assert "carp better" in section and "on par within" in section
    assert (tmp_path / "reports" / "figures" / "steps_to_success_lift.png").exists()
    claims = markdown.split("## The paper's claims on this run", 1)[1].split("\n## ", 1)[0]
    cells = [
        [cell.strip() for cell in line.split("|")[1:-1]] for line in claims.splitlines() if line.startswith("| lift")
    ]
    rows = {claim: verdict for _, claim, verdict, _ in cells}
    assert rows == {
        "CARP's success is on par with DP-C": "holds",
        "CARP's success is better than next-token's": "holds",
        "CARP is about 10x faster per chunk than DP-C": "holds",
    }
    assert "14.9x as long per chunk" in claims  # medians 45.03 and 3.03 ms


def test_a_run_without_several_families_states_no_claim(tmp_path, inputs):
    runs = {"lift": {"carp": _runs({0: 0.9}, chunk_ms=3.0)}}
    evaluation = {"lift": {"carp": pooled_metrics(runs["lift"]["carp"])}}
    markdown = write_report(
        dataclasses.replace(inputs, evaluation=evaluation, runs=runs, max_steps={"lift": 400}), tmp_path / "one"
    )[0].read_text()
    assert "## Comparison on lift" in markdown and "## The paper's claims" not in markdown


def test_a_tasks_precision_measure_gets_its_table_and_claim(tmp_path, inputs):
    generator = np.random.default_rng(0)
    three = {0: 0.8, 1: 0.8, 2: 0.8}
    runs = {"square": {"carp": _runs(three, 3.0), "diffusion_unet": _runs(three, 45.0, flip=3)}}
    for family, centre in (("carp", 5.0), ("diffusion_unet", 7.0)):
        for run in runs["square"][family].values():
            offsets = generator.normal(centre, 1.2, 100)
            offsets[::10] = np.nan  # episodes without a contact take no measure
            run.episodes["insertion_offset_mm"] = offsets
    evaluation = {"square": {family: pooled_metrics(seed_runs) for family, seed_runs in runs["square"].items()}}
    report = dataclasses.replace(inputs, evaluation=evaluation, runs=runs, max_steps={"square": 400})
    markdown = write_report(report, tmp_path / "reports")[0].read_text()
    section = markdown.split("## Comparison on square", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| insertion_offset_mm")]
    assert len(rows) == 2 and all("| 270 " in row for row in rows)  # 3 seeds x 90 measured episodes
    claims = markdown.split("## The paper's claims on this run", 1)[1]
    precision = next(line for line in claims.splitlines() if "insertion precision" in line)
    assert "| holds " in precision and "carp more precise" in precision
    # The precision test joins the success pair's correction: two groups, so its p at most doubles.
    raw, corrected = map(float, re.search(r"p = ([\d.e-]+), corrected ([\d.e-]+);", precision).groups())
    assert raw < corrected <= 2 * raw + 1e-3
    # With one seed per family the claim is not decided and takes no part in the correction.
    one_seed = {family: {0: seed_runs[0]} for family, seed_runs in runs["square"].items()}
    one = dataclasses.replace(report, runs={"square": one_seed})
    markdown = write_report(one, tmp_path / "one_seed")[0].read_text()
    claims = markdown.split("## The paper's claims on this run", 1)[1]
    precision = next(line for line in claims.splitlines() if "insertion precision" in line)
    assert "| not decided (1 training seed) " in precision and "corrected" not in precision


def test_the_seed_table_names_an_averaged_checkpoint_by_its_span():
    averaged = _runs({0: 0.9}, chunk_ms=3.0)
    averaged[0] = RunResults(dict(averaged[0].metrics) | {"averaged_checkpoints": 3}, averaged[0].episodes)
    table = seed_table({"carp": averaged, "diffusion_unet": _runs({0: 0.9}, chunk_ms=45.0)})
    assert table["checkpoint"].tolist() == [
        "mean of the last 3 of 4 candidates (to epoch 40)",
        "epoch 40 of 4 candidates",
    ]


def test_a_policy_that_never_succeeds_is_reported_with_its_interval(tmp_path, inputs):
    failing = summarize_episodes(
        successes=[False] * 50,
        steps=[300] * 50,
        crashed=[False] * 50,
        prediction_seconds=[0.007] * 10,
        decoding_seconds=[0.0003] * 10,
    )
    runs = dataclasses.replace(
        inputs, evaluation={"pusht": {"carp": failing | {"backend": "onnxruntime", "action_steps": 8}}}
    )
    markdown, _ = write_report(runs, tmp_path)
    assert "0/50" in markdown.read_text() and (tmp_path / "figures" / "success_vs_latency.png").exists()


def test_a_multi_task_policy_is_set_next_to_the_single_task_policy_of_its_family(tmp_path, inputs):
    assert "## Multi-task" not in write_report(inputs, tmp_path / "single")[0].read_text()
    multi = {"successes": 30, "episodes": 50}
    table = multitask_table(
        {"lift": {"carp": multi, "diffusion_unet": multi}, "can": {"carp": {"successes": 0, "episodes": 50}}},
        inputs.evaluation,
    )
    assert table[["task", "policy"]].values.tolist() == [["lift", "carp"], ["lift", "diffusion_unet"], ["can", "carp"]]
    lift_carp = table.iloc[0]
    assert lift_carp["multi-task success"] == "30/50 (60.0%)" and lift_carp["multi-task 95% interval"] == "46.2-72.4%"
    assert lift_carp["single-task success"] == "45/50 (90.0%)" and lift_carp["single-task 95% interval"] == "78.6-95.7%"
    # No single-task policy of the family on the task: nothing to set beside it.
    assert table.iloc[1]["single-task success"] == "-" and table.iloc[2]["single-task 95% interval"] == "-"
    assert table.iloc[2]["multi-task 95% interval"] == "0.0-7.1%"
    markdown = write_report(dataclasses.replace(inputs, multitask={"lift": {"carp": multi}}), tmp_path / "multi")[0]
    section = markdown.read_text().split("## Multi-task", 1)[1].split("\n## ", 1)[0]
    assert "| lift " in section and "30/50 (60.0%)" in section and "45/50 (90.0%)" in section


def test_each_multi_task_policy_is_tested_against_its_single_task_policy_on_the_shared_episodes(tmp_path, inputs):
    def seeds(rate):
        return {0: rate, 1: rate, 2: rate, 3: rate, 4: rate}

    single = {"lift": {"carp": _runs(seeds(0.95), 3.0)}, "can": {"carp": _runs(seeds(0.80), 3.0)}}
    multi = {
        "lift": {"carp": _runs(seeds(0.95), 3.0, flip=2)},  # the same rate on other episodes
        "can": {"carp": _runs(seeds(0.40), 3.0)},  # 40 episodes fewer a seed, every one of them paired
        "stack": {"carp": _runs(seeds(0.70), 3.0)},  # no single-task policy: no pair
    }
    for run in multi["can"]["carp"].values():
        run.episodes["insertion_offset_mm"] = np.linspace(1.0, 3.0, 100)
    decided = compare_multitask(single, multi, "-multitask", margin=0.05, alpha=0.05)
    assert {task: len(pairs) for task, pairs in decided.items()} == {"lift": 1, "can": 1, "stack": 0}
    can = decided["can"][0]
    assert (can.first, can.second, can.episodes, can.seeds) == ("carp-multitask", "carp", 100, 5)
    assert (can.networks[0].mcnemar.first_only, can.networks[0].mcnemar.second_only) == (0, 40)
    assert can.verdict == "carp better"
    lift = decided["lift"][0]
    assert lift.networks[0].mcnemar.first_only == lift.networks[0].mcnemar.second_only == 2
    # One correction over the two pairs, each pair counted once: Can's p of a difference is doubled.
    assert can.adjusted_p_value == pytest.approx(min(1.0, 2 * can.p_value))

    # A run that trained only the multi-task policies: no section per task, the pairs and measures still reported.
    evaluation = {
        task: {family: pooled_metrics(runs) for family, runs in families.items()} for task, families in single.items()
    }
    report = dataclasses.replace(
        inputs,
        evaluation={"lift": {}, "can": {}, "stack": {}},
        runs=single,
        multitask={
            task: {family: pooled_metrics(runs) for family, runs in families.items()}
            for task, families in multi.items()
        },
        multitask_runs=multi,
    )
    markdown = write_report(
        dataclasses.replace(report, evaluation={**report.evaluation, **evaluation}), tmp_path / "a"
    )[0]
    section = markdown.read_text().split("## Multi-task", 1)[1].split("\n## ", 1)[0]
    cells = [
        [cell.strip() for cell in line.split("|")[1:-1]]
        for line in section.splitlines()
        if line.startswith("| ") and "vs carp |" in line
    ]
    assert [row[:4] for row in cells] == [
        ["lift", "carp-multitask vs carp", "5", "100"],
        ["can", "carp-multitask vs carp", "5", "100"],
    ]
    assert "can, carp better:" in section and "lift, on par within" in section
    assert re.search(r"\| insertion_offset_mm +\| carp-multitask +\| 500 ", section)
    alone = write_report(dataclasses.replace(report, runs={}), tmp_path / "b")[0].read_text()
    assert "## Policies on" not in alone and "## Comparison on" not in alone
    assert re.search(r"\| stack +\| carp +\| 350/500 \(70.0%\)", alone)


def test_multi_task_policies_of_two_families_are_compared_with_each_other_and_the_claims_checked(tmp_path, inputs):
    def seeds(rate):
        return {0: rate, 1: rate, 2: rate, 3: rate, 4: rate}

    single = {"lift": {"carp": _runs(seeds(0.90), 3.0)}}
    multi = {
        "lift": {"carp": _runs(seeds(0.90), 3.0, flip=1), "diffusion_unet": _runs(seeds(0.90), 45.0, flip=2)},
        "can": {"carp": _runs(seeds(0.80), 3.0), "diffusion_unet": _runs(seeds(0.40), 45.0)},
    }
    decided = compare_multitask(single, multi, "-multitask", margin=0.05, alpha=0.05)
    # Lift: carp's multi-task policy against its single-task one, then the two multi-task policies; Can: only the
    # two multi-task policies (no single-task policy there).
    assert [(pair.first, pair.second) for pair in decided["lift"]] == [
        ("carp-multitask", "carp"),
        ("carp-multitask", "diffusion_unet-multitask"),
    ]
    can = decided["can"][0]
    network = can.networks[0]
    assert (can.first, can.second, network.mcnemar.first_only, network.mcnemar.second_only) == (
        "carp-multitask",
        "diffusion_unet-multitask",
        40,
        0,
    )
    assert can.verdict == "carp-multitask better"
    # One correction over the three multi-task pairs: the smallest p is tripled.
    assert can.adjusted_p_value == pytest.approx(min(1.0, 3 * can.p_value))

    report = dataclasses.replace(
        inputs,
        evaluation={task: {} for task in multi},
        runs=single,
        multitask={
            task: {family: pooled_metrics(runs) for family, runs in families.items()}
            for task, families in multi.items()
        },
        multitask_runs=multi,
        max_steps={"lift": 400, "can": 400},
    )
    markdown = write_report(report, tmp_path / "reports")[0].read_text()
    section = markdown.split("## Multi-task", 1)[1].split("\n## ", 1)[0]
    assert "can, carp-multitask better:" in section
    claims = {
        (cells[0], cells[1]): cells[2]
        for cells in (
            [cell.strip() for cell in line.split("|")[1:-1]] for line in section.splitlines() if line.startswith("| ")
        )
        if len(cells) == 4 and cells[1].startswith("CARP")
    }
    assert claims == {
        ("lift", "CARP's success is on par with DP-C"): "holds",
        ("can", "CARP's success is on par with DP-C"): "holds",
        ("lift", "CARP is about 10x faster per chunk than DP-C"): "holds",
        ("can", "CARP is about 10x faster per chunk than DP-C"): "holds",
    }
