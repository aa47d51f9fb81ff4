"""A kind's artifact: saved with the pipeline's metadata, reloaded, hashed, checked against the params, registered."""

import json

import mlflow
import numpy as np
import pytest
import torch

from carp.data.normalizer import MinMaxNormalizer
from carp.tokenizer.artifact import METADATA_FILENAME, NonFiniteTokenizerError, TokenizerMismatchError
from carp.tokenizer.kinds.artifact import (
    KindArtifact,
    artifact_kind,
    check_fits_params,
    is_kind_artifact,
    load_any_artifact,
    load_kind_artifact,
    save_kind_artifact,
)
from carp.tokenizer.kinds.evaluation import evaluate_kind, round_trip_trajectory
from carp.tracking.registry import KIND_TAG, fetch_registered_tokenizer, register_tokenizer, registered_model_name
from carp.tracking.runs import stage_run
from tests.tokenizer.kinds.conftest import A, H, fitted

LIFT = MinMaxNormalizer(minimum=np.full(A, -2.0), maximum=np.full(A, 2.0))
FITS = ("fast", "panda-test3", H, (1, 2), 8)


@pytest.fixture(scope="module")
def fast(training_chunks):
    return fitted("fast", training_chunks)


def test_a_saved_kind_reloads_with_its_statistics_metrics_and_hash(tmp_path, fast, held_out_chunks):
    sha = save_kind_artifact(tmp_path / "tok", fast, {"lift": LIFT}, "panda-test3", {"rmse_percent_range/mean": 1.5})
    loaded = load_any_artifact(tmp_path / "tok")
    assert isinstance(loaded, KindArtifact) and is_kind_artifact(tmp_path / "tok")
    assert (loaded.sha256, loaded.kind, artifact_kind(loaded), loaded.tasks) == (sha, "fast", "fast", ["lift"])
    assert loaded.metrics == {"rmse_percent_range/mean": 1.5}
    assert np.array_equal(loaded.action_normalizer().maximum, LIFT.maximum)
    assert torch.equal(loaded.tokenizer.encode(held_out_chunks).ids, fast.encode(held_out_chunks).ids)
    # The same files hash alike, whatever the metrics say; a copy from the loaded folder keeps the hash.
    again = save_kind_artifact(tmp_path / "copy", loaded.tokenizer, {"lift": LIFT}, "panda-test3", {}, loaded.directory)
    assert again == sha


def test_changed_files_or_another_recorded_hash_are_refused(tmp_path, fast):
    directory = tmp_path / "tok"
    sha = save_kind_artifact(directory, fast, {"lift": LIFT}, "panda-test3")
    with pytest.raises(TokenizerMismatchError, match=f"not the sha256 {'0' * 12}... recorded in models/ref.json"):
        load_kind_artifact(directory, "0" * 64, "models/ref.json")
    metadata = json.loads((directory / METADATA_FILENAME).read_text())
    metadata["action_normalizers"]["lift"]["maximum"][0] = 3.0
    (directory / METADATA_FILENAME).write_text(json.dumps(metadata))
    with pytest.raises(TokenizerMismatchError, match=f"not the sha256 {sha[:12]}"):
        load_kind_artifact(directory)


def test_a_metric_that_is_not_finite_is_never_saved(tmp_path, fast):
    with pytest.raises(NonFiniteTokenizerError, match="metric bits_per_chunk=nan: not finite"):
        save_kind_artifact(tmp_path / "tok", fast, {"lift": LIFT}, "panda-test3", {"bits_per_chunk": float("nan")})
    assert not (tmp_path / "tok").exists()


@pytest.mark.parametrize(
    ("fits", "message"),
    [
        (("binning", *FITS[1:]), "tokenizer.kind is 'fast' in the tokenizer but the params ask for 'binning'"),
        (("fast", "panda-abs10", *FITS[2:]), "action space is 'panda-test3' in the tokenizer but the params ask for"),
        (("fast", "panda-test3", 8, *FITS[3:]), "data.action_horizon is 16 in the tokenizer but the params ask for 8"),
    ],
)
def test_a_kind_that_does_not_fit_the_params_is_refused_naming_the_key_and_both_values(tmp_path, fast, fits, message):
    save_kind_artifact(tmp_path / "tok", fast, {"lift": LIFT}, "panda-test3")
    artifact = load_any_artifact(tmp_path / "tok")
    check_fits_params(artifact, *FITS)
    with pytest.raises(TokenizerMismatchError, match=message):
        check_fits_params(artifact, *fits)


def test_the_stage_metrics_measure_rate_and_distortion_and_draw_the_episode(tmp_path, fast, held_out_chunks):
    raw = {"lift": LIFT.unnormalize(held_out_chunks.double().numpy())}
    episode = LIFT.unnormalize(held_out_chunks[:3].reshape(-1, A).double().numpy())[:40]
    metrics, timings = evaluate_kind(fast, raw, {"lift": LIFT}, ("lift", episode), tmp_path / "figure.png")
    assert (tmp_path / "figure.png").exists() and set(timings) == {"encode_ms", "decode_ms"}
    assert metrics["vocabulary_size"] == fast.vocabulary_size and metrics["invalid_rate"] == 0.0
    assert metrics["rmse_percent_range/mean"] < 5.0 and set(metrics) >= {f"rmse_percent_range/dim{d}" for d in range(A)}
    assert metrics["bits_per_chunk"] == pytest.approx(metrics["tokens_per_chunk/mean"] * np.log2(fast.vocabulary_size))
    # Rerunning on the same tokenizer gives the same metrics: they go into a DVC metrics file.
    assert evaluate_kind(fast, raw, {"lift": LIFT}, ("lift", episode), tmp_path / "again.png")[0] == metrics
    assert round_trip_trajectory(fast, torch.zeros(21, A)).shape == (21, A)


def test_a_kind_is_registered_under_its_kind_and_action_space_and_fetched_back(tmp_path, fast, held_out_chunks):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    directory = tmp_path / "tok"
    sha = save_kind_artifact(directory, fast, {"lift": LIFT}, "panda-test3")
    name = registered_model_name("panda-test3", "fast")
    assert (
        name == "carp-tokenizer-fast-panda-test3"
        and registered_model_name("panda-test3") == "carp-tokenizer-panda-test3"
    )
    with stage_run(uri, "carp-tokenizer", "register_tokenizer", {"a": "1"}, {}) as run:
        reference = register_tokenizer(uri, directory, name, "default", run.run_id, sha)
    version = mlflow.MlflowClient(tracking_uri=uri).get_model_version(name, reference.version)
    assert version.tags[KIND_TAG] == "fast" and version.tags["carp.action_space"] == "panda-test3"
    artifact, fetched = fetch_registered_tokenizer(uri, reference.uri)
    assert isinstance(artifact, KindArtifact) and fetched.sha256 == sha == artifact.sha256
    assert torch.equal(artifact.tokenizer.encode(held_out_chunks).ids, fast.encode(held_out_chunks).ids)


def test_a_policy_family_that_takes_no_other_kind_refuses_it_in_one_line(tmp_path, fast):
    from carp.tracking.registry import TokenizerReference
    from carp.training.policy_inputs import ReferencedTokenizer

    sha = save_kind_artifact(tmp_path / "tokenizer", fast, {"lift": LIFT}, "panda-test3")
    TokenizerReference("carp-tokenizer-fast-panda-test3", "1", "default", "run", sha).save(tmp_path / "ref.json")
    referenced = ReferencedTokenizer(tmp_path / "tokenizer", tmp_path / "ref.json", "panda-test3", (1, 2), 8)
    with pytest.raises(TokenizerMismatchError) as raised:
        referenced.load()
    assert str(raised.value) == (
        f"{tmp_path / 'tokenizer'}: a 'fast' tokenizer (tokenizer.kind); this policy family trains beside carp_msvq "
        "only (next_token takes any kind)"
    )


def test_a_family_that_takes_the_kind_loads_it_checked_against_the_reference_and_action_space(tmp_path, fast):
    from carp.config.tokenizer_kinds import TOKENIZER_KINDS
    from carp.tracking.registry import TokenizerReference
    from carp.training.policy_inputs import ReferencedTokenizer

    sha = save_kind_artifact(tmp_path / "tokenizer", fast, {"lift": LIFT}, "panda-test3")
    TokenizerReference("carp-tokenizer-fast-panda-test3", "1", "default", "run", sha).save(tmp_path / "ref.json")
    directory, reference = tmp_path / "tokenizer", tmp_path / "ref.json"
    _, artifact = ReferencedTokenizer(directory, reference, "panda-test3", (1, 2), 8, TOKENIZER_KINDS).load()
    assert isinstance(artifact, KindArtifact) and artifact.kind == "fast" and artifact.sha256 == sha
    with pytest.raises(TokenizerMismatchError, match="action space is 'panda-test3' in the tokenizer"):
        ReferencedTokenizer(directory, reference, "panda-other", (1, 2), 8, TOKENIZER_KINDS).load()
