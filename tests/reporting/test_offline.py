"""The report's section for a task without a simulator: it says no rollout was possible and gives each family's
held-out action error as a mean over training seeds with its t interval, per dimension and per horizon step."""

from carp.reporting.offline import offline_detail_table, offline_family_table
from carp.reporting.report import ReportInputs, write_report


def summary(error: float) -> dict:
    """An offline evaluation summary (`carp.evaluation.offline.offline_evaluation`) of H = 2, A = 2."""
    return {
        "evaluation": "offline",
        "held_out_episodes": 1,
        "action_rmse": error,
        "executed_action_rmse": error / 2,
        "step_rmse/1": error + 1,
        "step_rmse/0": error,
        "dimension_rmse/x": error,
        "dimension_rmse/y": 3 * error,
    }


RUNS = {
    "carp": {0: summary(1.0), 1: summary(2.0), 2: summary(3.0)},
    "diffusion_unet": {0: summary(0.5)},
}


def test_the_family_table_gives_seed_means_and_t_intervals():
    table = offline_family_table(RUNS).set_index("policy")
    assert table.loc["carp", "seeds"] == 3 and table.loc["diffusion_unet", "held-out episodes"] == 1
    assert table.loc["carp", "RMSE, whole chunk"] == "2"
    # Seeds 1, 2, 3: t interval 2 +- 2.484, clipped at 0.
    assert table.loc["carp", "95% interval, whole chunk"] == "0-4.484"
    assert table.loc["carp", "95% interval, executed rows"] == "0-2.242"
    assert table.loc["diffusion_unet", "95% interval, whole chunk"] == "-"  # one seed: no interval
    assert "90% interval, whole chunk" in offline_family_table(RUNS, level=0.9).columns


def test_the_detail_tables_give_seed_means_per_dimension_and_per_step_in_order():
    dimensions = offline_detail_table(RUNS, "dimension_rmse/").set_index("policy")
    assert list(dimensions.columns) == ["x", "y"] and dimensions.loc["carp", "y"] == "6"
    steps = offline_detail_table(RUNS, "step_rmse/").set_index("policy")
    assert list(steps.columns) == ["0", "1"] and steps.loc["diffusion_unet", "1"] == "1.5"


def test_a_run_of_tasks_without_a_simulator_reports_offline_only(tmp_path):
    markdown_path, html_path = write_report(ReportInputs(evaluation={}, offline={"my_robot": RUNS}), tmp_path)
    markdown = markdown_path.read_text()
    assert "## Offline evaluation on my_robot" in markdown
    assert "No rollout was possible: my_robot has no simulator" in markdown
    assert "0-4.484" in markdown and "## Success rate" not in markdown and "## Inference latency" not in markdown
    assert "Offline evaluation on my_robot" in html_path.read_text()
