import dataclasses

import optuna
import pytest
from mlflow import MlflowClient

from carp.sweep.claims import ClaimStore
from carp.sweep.study import PARENT_RUN_ATTR, run_sweep
from carp.sweep.tracking import SweepTracker
from tests.sweep.conftest import FakeRunner


@pytest.mark.slow
def test_one_parent_run_per_study_and_one_child_per_trial(sweep_config, tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    runner = FakeRunner(errors={4: 10.0, 8: 25.0})
    first = run_sweep(
        dataclasses.replace(sweep_config, num_trials=2), runner, tmp_path, SweepTracker(uri, "carp-sweep", {"k": "v"})
    )
    study = optuna.load_study(study_name="unit", storage=sweep_config.storage)
    parent_id = study.user_attrs[PARENT_RUN_ATTR]
    result = run_sweep(sweep_config, runner, tmp_path, SweepTracker(uri, "carp-sweep", {"k": "v"}))
    assert first.finished_trials == 2 and result.finished_trials == 3
    assert optuna.load_study(study_name="unit", storage=sweep_config.storage).user_attrs[PARENT_RUN_ATTR] == parent_id

    client = MlflowClient(tracking_uri=uri)
    experiment = client.get_experiment_by_name("carp-sweep")
    runs = client.search_runs([experiment.experiment_id])
    parents = [run for run in runs if "mlflow.parentRunId" not in run.data.tags]
    children = [run for run in runs if run.data.tags.get("mlflow.parentRunId") == parent_id]
    assert [run.info.run_id for run in parents] == [parent_id]  # the resume reused it
    assert len(children) == 3 and len(runs) == 4
    parent = parents[0]
    assert parent.info.status == "FINISHED" and parent.data.tags["k"] == "v"
    assert parent.data.params["codebook_sizes"] == "[4, 8]"
    assert parent.data.tags["carp.best_params"] == result.best.settings.command_line()
    assert parent.data.metrics["best_validation_success_rate"] == result.best.validation_success_rate

    by_number = {int(run.data.tags["carp.trial_number"]): run for run in children}
    for record in result.records:
        run = by_number[record.number]
        assert run.info.run_name == f"trial-{record.number}" and run.data.tags["k"] == "v"
        assert run.data.tags["carp.trial_state"] == record.state
        assert run.data.params["codebook_size"] == str(record.settings.codebook_size)
        assert run.data.params["num_scales"] == str(record.settings.num_scales)
        assert run.data.metrics["tokenizer_rmse_percent"] == record.tokenizer_rmse_percent
        if record.state == "COMPLETE":
            assert run.info.status == "FINISHED"
            assert run.data.metrics["validation_success_rate"] == record.validation_success_rate
            assert run.data.tags["carp.dvc_experiment"] == record.dvc_experiment
        else:
            assert record.state == "PRUNED" and run.info.status == "KILLED"
            assert "validation_success_rate" not in run.data.metrics


@pytest.mark.slow
def test_a_worker_that_loses_the_race_for_the_parent_run_joins_the_stored_one(sweep_config, tmp_path):
    # Another worker created the study's parent run and stored it first, while this one was creating its own.
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    storage = optuna.storages.RDBStorage(sweep_config.storage)
    optuna.create_study(study_name="unit", storage=storage, direction="maximize")
    other = SweepTracker(uri, "carp-sweep", {}).open_study("unit", None, {"study_name": "unit"})
    claims = ClaimStore(sweep_config.storage, storage.get_study_id_from_name("unit"))
    assert claims.setdefault(PARENT_RUN_ATTR, other) == other
    claims.close()

    run_sweep(sweep_config, FakeRunner(), tmp_path, SweepTracker(uri, "carp-sweep", {}))
    client = MlflowClient(tracking_uri=uri)
    runs = client.search_runs([client.get_experiment_by_name("carp-sweep").experiment_id])
    assert [run.info.run_id for run in runs if "mlflow.parentRunId" not in run.data.tags] == [other]
    assert len(runs) == 1 + sweep_config.num_trials  # the losing parent run was deleted
    assert {run.data.tags["mlflow.parentRunId"] for run in runs if run.info.run_id != other} == {other}
    assert optuna.load_study(study_name="unit", storage=sweep_config.storage).user_attrs[PARENT_RUN_ATTR] == other
