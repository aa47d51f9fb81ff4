import json
import subprocess
import sys
import tempfile
import types

import mlflow
import numpy as np
import pytest
import torch

from carp.config import ConfigError
from carp.data.normalizer import MinMaxNormalizer
from carp.data.sources import file_sha256
from carp.serving.startup import load_served_model
from carp.tokenizer.artifact import (
    NonFiniteTokenizerError,
    TokenizerMismatchError,
    check_compatible,
    load_tokenizer_artifact,
    save_tokenizer_artifact,
)
from carp.tokenizer.spec import TokenizerSpec
from carp.tokenizer.tokenizer import MultiScaleActionTokenizer
from carp.tracking.registry import (
    SHA_TAG,
    TokenizerReference,
    evaluation_tags,
    fetch_registered_tokenizer,
    policy_aliases,
    register_confirmed_policy,
    register_tokenizer,
    resolve_alias,
    set_version_tag,
)
from carp.tracking.runs import find_runs, stage_run
from tests.serving.conftest import save_tiny_checkpoint

SPEC = TokenizerSpec(action_dim=2, action_horizon=8, scales=(1, 2), codebook_size=8, latent_channels=4)


LIFT_BOUNDS = MinMaxNormalizer(minimum=np.array([-1.0, 0.0]), maximum=np.array([1.0, 2.0]))
CAN_BOUNDS = MinMaxNormalizer(minimum=np.array([0.0, 0.0]), maximum=np.array([4.0, 1.0]))


def make_artifact(directory, seed=0, normalizers=None):
    torch.manual_seed(seed)
    tokenizer = MultiScaleActionTokenizer(SPEC)
    sha = save_tokenizer_artifact(directory, tokenizer, normalizers or {"lift": LIFT_BOUNDS}, "panda-test2")
    return tokenizer, sha


def register(uri, directory, sha, alias="default"):
    with stage_run(uri, "carp-tokenizer", "register_tokenizer", {"a": "1"}, {"carp.dvc_stage": "register"}) as run:
        return register_tokenizer(uri, directory, "carp-tokenizer-panda-test2", alias, run.run_id, sha)


@pytest.mark.slow
def test_registry_round_trip_idempotence_and_new_process_load(tmp_path, monkeypatch):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    directory = tmp_path / "tokenizer"
    tokenizer, sha = make_artifact(directory)
    first = register(uri, directory, sha)
    again = register(uri, directory, sha)
    assert first.version == again.version == "1"
    assert first.sha256 == sha and first.uri == "models:/carp-tokenizer-panda-test2@default"
    assert len(find_runs(uri, "carp-tokenizer")) == 2
    assert (tmp_path / "mlartifacts").exists()  # artifacts beside the store, not in the working directory

    other_directory = tmp_path / "other"
    other_tokenizer, other_sha = make_artifact(
        other_directory, seed=1, normalizers={"lift": LIFT_BOUNDS, "can": CAN_BOUNDS}
    )
    assert other_sha != sha
    assert register(uri, other_directory, other_sha, alias="candidate").version == "2"

    actions = torch.rand(5, 8, 2) * 2 - 1
    expected = tokenizer.encode_to_sequence(actions).tolist()
    script = (
        "import json, sys, torch\n"
        "from carp.tracking.registry import fetch_registered_tokenizer\n"
        "artifact, ref = fetch_registered_tokenizer(sys.argv[1], 'models:/carp-tokenizer-panda-test2@default')\n"
        "actions = torch.tensor(json.loads(sys.argv[2]))\n"
        "print(json.dumps({'ids': artifact.tokenizer.encode_to_sequence(actions).tolist(), 'version': ref.version}))\n"
    )
    output = subprocess.run(
        [sys.executable, "-c", script, uri, json.dumps(actions.tolist())], capture_output=True, text=True, check=True
    )
    loaded = json.loads(output.stdout.strip().splitlines()[-1])
    assert loaded == {"ids": expected, "version": "1"}

    # The pyfunc face: raw actions in, the same token sequence out (the model normalizes with its own bounds).
    mlflow.set_tracking_uri(uri)
    pyfunc_model = mlflow.pyfunc.load_model("models:/carp-tokenizer-panda-test2@default")
    raw_actions = actions.numpy() + np.array([0.0, 1.0], dtype=np.float32)  # normalized [-1, 1] -> [-1, 1] x [0, 2]
    assert pyfunc_model.predict(raw_actions).tolist() == expected

    downloads = tmp_path / "downloads"
    downloads.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(downloads))
    candidate, reference = fetch_registered_tokenizer(uri, "models:/carp-tokenizer-panda-test2@candidate")
    assert list(downloads.iterdir()) == []  # the temporary download is gone once the weights are loaded
    assert reference.version == "2" and candidate.sha256 == other_sha and candidate.tasks == ["lift", "can"]
    # A two-task tokenizer normalizes raw actions with the statistics of the task named at inference.
    two_task_model = mlflow.pyfunc.load_model("models:/carp-tokenizer-panda-test2@candidate")
    can_actions = (actions.numpy() + 1) / 2 * np.array([4.0, 1.0], dtype=np.float32)  # [-1, 1] -> [0, 4] x [0, 1]
    expected_can = other_tokenizer.encode_to_sequence(actions).tolist()
    assert two_task_model.predict(can_actions, params={"task": "can"}).tolist() == expected_can
    with pytest.raises(KeyError, match=r"trained on \['lift', 'can'\]: name the task"):
        two_task_model.predict(can_actions)
    with pytest.raises(LookupError, match="not found in the registry"):
        fetch_registered_tokenizer(uri, "models:/carp-tokenizer-panda-test2@nope")


def test_sha_mismatch_and_incompatible_params_are_refused(tmp_path):
    directory = tmp_path / "tokenizer"
    _, sha = make_artifact(directory)
    artifact = load_tokenizer_artifact(directory, expected_sha256=sha)
    assert artifact.sha256 == sha
    with pytest.raises(
        TokenizerMismatchError,
        match=rf"tokenizer.pt: tokenizer weights have sha256 {sha[:12]}\.\.\., not the sha256 000000000000\.\.\. "
        "recorded in the reference",
    ):
        load_tokenizer_artifact(directory, expected_sha256="0" * 64)
    check_compatible(artifact, "panda-test2", (1, 2), 8)
    with pytest.raises(TokenizerMismatchError, match=r"tokenizer scales is \[1, 2\] but the params ask for \[2\]"):
        check_compatible(artifact, "panda-test2", (2,), 8)
    # A schedule that extends the latent (or stops short of it) is another tokenizer too.
    for schedule in ((1, 2, 3), (1,)):
        with pytest.raises(TokenizerMismatchError, match=r"tokenizer scales is \[1, 2\] but the params ask for"):
            check_compatible(artifact, "panda-test2", schedule, 8)
    with pytest.raises(TokenizerMismatchError, match="codebook_size is 8 but the params ask for 256"):
        check_compatible(artifact, "panda-test2", (1, 2), 256)
    with pytest.raises(
        TokenizerMismatchError, match="action space is 'panda-test2' but the params ask for 'panda-abs10'"
    ):
        check_compatible(artifact, "panda-abs10", (1, 2), 8)


def test_each_training_task_keeps_its_own_action_statistics(tmp_path):
    _, sha = make_artifact(tmp_path / "two", normalizers={"lift": LIFT_BOUNDS, "can": CAN_BOUNDS})
    artifact = load_tokenizer_artifact(tmp_path / "two", expected_sha256=sha)
    assert artifact.tasks == ["lift", "can"]
    assert artifact.action_normalizer("can").maximum.tolist() == [4.0, 1.0]
    with pytest.raises(KeyError, match=r"task 'square' is not one of the tokenizer's training tasks"):
        artifact.action_normalizer("square")
    with pytest.raises(KeyError, match="name the task whose action statistics to use"):
        artifact.action_normalizer()
    # Same weights, other statistics or task names: another artifact, another hash.
    _, lift_only = make_artifact(tmp_path / "one")
    _, renamed = make_artifact(tmp_path / "renamed", normalizers={"square": LIFT_BOUNDS})
    assert len({sha, lift_only, renamed}) == 3
    assert load_tokenizer_artifact(tmp_path / "one").action_normalizer().minimum.tolist() == [-1.0, 0.0]


def test_an_artifact_with_one_normalization_for_all_tasks_is_refused(tmp_path):
    make_artifact(tmp_path)
    path = tmp_path / "tokenizer.pt"
    payload = torch.load(path, weights_only=False)
    payload["action_normalizer"] = payload.pop("action_normalizers")["lift"]
    torch.save(payload, path)
    with pytest.raises(TokenizerMismatchError, match="one action normalization for all its tasks"):
        load_tokenizer_artifact(tmp_path)


@pytest.mark.parametrize(
    "broken, message",
    [
        ("weight", r"weight encoder\..*: holds NaN or inf"),
        ("metric", r"metric rmse_percent_range/mean=inf: not finite"),
        ("statistics", r"action statistics of lift: maximum=\[1.0, 1e\+39\]: not finite"),
    ],
)
def test_a_non_finite_tokenizer_is_neither_saved_nor_loaded_nor_registered(tmp_path, broken, message):
    torch.manual_seed(0)
    tokenizer = MultiScaleActionTokenizer(SPEC)
    normalizers = {"lift": LIFT_BOUNDS}
    metrics = {"rmse_percent_range/mean": 1.5}
    if broken == "weight":
        next(p for name, p in tokenizer.named_parameters() if name.startswith("encoder")).data[0] = float("nan")
    elif broken == "metric":
        metrics["rmse_percent_range/mean"] = float("inf")
    else:
        normalizers = {"lift": MinMaxNormalizer(minimum=np.array([-1.0, 0.0]), maximum=np.array([1.0, 1e39]))}
    with pytest.raises(NonFiniteTokenizerError, match=message):
        save_tokenizer_artifact(tmp_path / "refused", tokenizer, normalizers, "panda-test2", metrics)
    assert not (tmp_path / "refused").exists()

    # An artifact written before these checks existed: refused on load, so never registered or aliased.
    directory = tmp_path / "tokenizer"
    sha = save_tokenizer_artifact(directory, MultiScaleActionTokenizer(SPEC), {"lift": LIFT_BOUNDS}, "panda-test2")
    payload = torch.load(directory / "tokenizer.pt", weights_only=False)
    if broken == "weight":
        payload["state_dict"] = tokenizer.state_dict()
    elif broken == "metric":
        payload["metrics"] = metrics
    else:
        payload["action_normalizers"] = {task: n.to_dict() for task, n in normalizers.items()}
    torch.save(payload, directory / "tokenizer.pt")
    with pytest.raises(NonFiniteTokenizerError, match=message):
        load_tokenizer_artifact(directory)
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    with pytest.raises(NonFiniteTokenizerError, match=message):
        register_tokenizer(uri, directory, "carp-tokenizer-panda-test2", "default", "no-run", sha)
    assert not (tmp_path / "mlflow.db").exists()


def test_metrics_are_stored_with_the_tokenizer(tmp_path):
    torch.manual_seed(0)
    metrics = {"rmse_percent_range/mean": 1.5, "perplexity/mean": 6.0}
    save_tokenizer_artifact(tmp_path, MultiScaleActionTokenizer(SPEC), {"lift": LIFT_BOUNDS}, "panda-test2", metrics)
    assert load_tokenizer_artifact(tmp_path).metrics == metrics
    assert json.loads((tmp_path / "tokenizer.json").read_text())["metrics"] == metrics


def test_reference_file_round_trip(tmp_path):
    reference = TokenizerReference("carp-tokenizer-x", "3", "default", "run", "f" * 64)
    reference.save(tmp_path / "ref.json")
    assert TokenizerReference.load(tmp_path / "ref.json") == reference


EVALUATION = {"training_seed": 0, "selected_epoch": 1, "selection": "lowest_loss", "success_rate": 0.5, "episodes": 4}
"""An evaluation summary's registered part: the lowest training loss picked epoch 1's snapshot."""


def test_each_seed_gets_its_own_alias_and_the_first_seed_the_plain_one():
    assert policy_aliases("candidate", 3, (3, 0)) == ("candidate-seed3", "candidate")
    assert policy_aliases("candidate", 0, (3, 0)) == ("candidate-seed0",)


def test_the_version_tags_come_from_the_evaluation_summary():
    assert evaluation_tags(EVALUATION | {"successes": 2}) == {
        "carp.training_seed": "0",
        "carp.selected_epoch": "1",
        "carp.selection": "lowest_loss",
        "carp.test_success_rate": "0.5",
        "carp.test_episodes": "4",
    }
    with pytest.raises(ValueError, match=r"the evaluation summary lacks \['selection'\]"):
        evaluation_tags({key: value for key, value in EVALUATION.items() if key != "selection"})


def _summary(path, evaluation):
    path.write_text(json.dumps(evaluation))
    return path


def test_a_reserved_alias_or_a_summary_that_does_not_fit_is_refused_before_anything_is_registered(tmp_path):
    save_tiny_checkpoint(tmp_path / "policy.pt")
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    summary = _summary(tmp_path / "seed0.json", EVALUATION)
    with pytest.raises(ConfigError, match="alias='v2': 'latest', 'v<digits>'"):
        register_confirmed_policy(uri, tmp_path, [0.1, 0.3], summary, ("candidate", "v2"))
    # Epoch 1 is no candidate: the run kept no snapshot.
    with pytest.raises(ValueError, match=rf"^{summary}: the evaluation selected epoch 1, which is not among the run's"):
        register_confirmed_policy(uri, tmp_path, [0.1, 0.3], summary, ("candidate",))
    assert not (tmp_path / "mlflow.db").exists()


def _register_seed(uri, run_dir, seed, evaluation=EVALUATION):
    summary = _summary(run_dir.with_suffix(".json"), evaluation | {"training_seed": seed})
    with stage_run(uri, "carp-lift", f"register_policy@lift-carp-{seed}", {}, {}):
        return register_confirmed_policy(uri, run_dir, [0.1, 0.3], summary, policy_aliases("candidate", seed, (0, 1)))


@pytest.mark.slow
def test_the_confirmed_checkpoint_is_registered_once_tagged_and_served_from_its_alias(tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    runs = {}
    for seed in (0, 1):
        runs[seed] = tmp_path / f"seed{seed}"
        save_tiny_checkpoint(runs[seed] / "snapshots" / "epoch0001.pt", seed=2 * seed)
        save_tiny_checkpoint(runs[seed] / "policy.pt", seed=2 * seed + 1)
    first = _register_seed(uri, runs[0], 0)
    snapshot_sha = file_sha256(runs[0] / "snapshots" / "epoch0001.pt")
    assert (first.name, first.version, first.alias, first.sha256) == (
        "carp-policy-lift-carp",
        "1",
        "candidate-seed0",
        snapshot_sha,
    )
    # The same bytes again, evaluated on more episodes: the same version, its tags follow the latest evaluation.
    again = _register_seed(uri, runs[0], 0, EVALUATION | {"success_rate": 0.75, "episodes": 8})
    assert again == first
    assert _register_seed(uri, runs[1], 1).version == "2"

    client = mlflow.MlflowClient(tracking_uri=uri)
    assert len(client.search_model_versions("name = 'carp-policy-lift-carp'")) == 2
    for alias, version in (("candidate", "1"), ("candidate-seed0", "1"), ("candidate-seed1", "2")):
        assert resolve_alias(uri, f"models:/carp-policy-lift-carp@{alias}").version == version, alias
    assert client.get_model_version("carp-policy-lift-carp", "1").tags == {
        SHA_TAG: snapshot_sha,
        "carp.training_seed": "0",
        "carp.selected_epoch": "1",
        "carp.selection": "lowest_loss",
        "carp.test_success_rate": "0.75",
        "carp.test_episodes": "8",
    }
    assert client.get_model_version("carp-policy-lift-carp", "2").tags["carp.training_seed"] == "1"

    served, _ = load_served_model("models:/carp-policy-lift-carp@candidate", tracking_uri=uri)
    assert (served.source.sha256, served.source.version, served.source.alias) == (snapshot_sha, "1", "candidate")


class _RacingClient:
    """A registry client whose first tag writes fail as PostgreSQL fails the second of two concurrent inserts."""

    def __init__(self, failures: int, other_writer_value: str | None) -> None:
        self.failures, self.other_writer_value, self.tags, self.writes = failures, other_writer_value, {}, 0

    def set_model_version_tag(self, name, version, key, value):
        self.writes += 1
        if self.failures:
            self.failures -= 1
            if self.other_writer_value is not None:
                self.tags[key] = self.other_writer_value
            raise mlflow.exceptions.MlflowException("duplicate key value violates unique constraint")
        self.tags[key] = value

    def get_model_version(self, name, version):
        return types.SimpleNamespace(tags=dict(self.tags))


def test_a_tag_another_writer_set_to_the_same_value_is_accepted_and_a_different_one_written_again():
    same = _RacingClient(failures=1, other_writer_value="panda-abs10")
    set_version_tag(same, "m", "1", "carp.action_space", "panda-abs10")
    assert same.writes == 1 and same.tags == {"carp.action_space": "panda-abs10"}
    other = _RacingClient(failures=2, other_writer_value="panda-delta10")
    set_version_tag(other, "m", "1", "carp.action_space", "panda-abs10")
    assert other.writes == 3 and other.tags == {"carp.action_space": "panda-abs10"}
