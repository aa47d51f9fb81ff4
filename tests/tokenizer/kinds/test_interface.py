"""What every kind promises: shapes, a deterministic round trip, saving, the rate it reports."""

import json
import math

import pytest
import torch

from carp.tokenizer.kinds.base import KIND_FILENAME, PADDING_ID, ActionTokenizer, TokenBatch
from carp.tokenizer.kinds.registry import kind_class, kind_names, load_tokenizer
from carp.tokenizer.rate_distortion import measure_rate_distortion
from tests.tokenizer.kinds.conftest import A, H, fitted

KINDS = kind_names()


@pytest.fixture(scope="module", params=KINDS)
def tokenizer(request, training_chunks):
    return fitted(request.param, training_chunks)


def test_every_kind_implements_the_interface(tokenizer):
    assert isinstance(tokenizer, ActionTokenizer)
    assert (tokenizer.action_dim, tokenizer.action_horizon) == (A, H)
    assert tokenizer.kind in KINDS


def test_tokens_have_the_documented_shapes_and_range(tokenizer, held_out_chunks):
    tokens = tokenizer.encode(held_out_chunks)
    assert tokens.ids.dtype == torch.long and tokens.lengths.dtype == torch.long
    assert tokens.ids.shape == (len(held_out_chunks), int(tokens.lengths.max()))
    assert tokens.lengths.shape == (len(held_out_chunks),)
    for row, length in zip(tokens.ids, tokens.lengths.tolist(), strict=True):
        assert ((row[:length] >= 0) & (row[:length] < tokenizer.vocabulary_size)).all()
        assert (row[length:] == PADDING_ID).all()
    if tokenizer.kind != "fast":
        assert (tokens.lengths == tokenizer.tokens_per_chunk.maximum).all()
    decoded = tokenizer.decode(tokens)
    assert decoded.actions.shape == held_out_chunks.shape and decoded.actions.dtype == torch.float32
    assert decoded.invalid.shape == (len(held_out_chunks),) and decoded.invalid_count == 0


def test_the_round_trip_is_deterministic(tokenizer, held_out_chunks):
    first, second = tokenizer.encode(held_out_chunks), tokenizer.encode(held_out_chunks)
    assert torch.equal(first.ids, second.ids) and torch.equal(first.lengths, second.lengths)
    assert torch.equal(tokenizer.decode(first).actions, tokenizer.decode(second).actions)


@pytest.mark.parametrize("kind", [kind for kind in KINDS if kind != "carp_msvq"])
def test_fitting_twice_gives_the_same_tokenizer(kind, training_chunks, held_out_chunks):
    one, other = fitted(kind, training_chunks), fitted(kind, training_chunks)
    assert torch.equal(one.encode(held_out_chunks).ids, other.encode(held_out_chunks).ids)


def test_a_saved_tokenizer_loads_as_the_same_kind_with_the_same_tokens(tokenizer, held_out_chunks, tmp_path):
    tokenizer.save(tmp_path)
    recorded = json.loads((tmp_path / KIND_FILENAME).read_text())
    assert recorded["kind"] == tokenizer.kind and recorded["format_version"] == 1
    loaded = load_tokenizer(tmp_path)
    assert type(loaded) is type(tokenizer)
    tokens = tokenizer.encode(held_out_chunks)
    assert torch.equal(loaded.encode(held_out_chunks).ids, tokens.ids)
    assert torch.equal(loaded.decode(tokens).actions, tokenizer.decode(tokens).actions)
    assert loaded.vocabulary_size == tokenizer.vocabulary_size


def test_a_folder_of_another_kind_is_refused(tokenizer, tmp_path):
    tokenizer.save(tmp_path)
    other = next(kind for kind in KINDS if kind != tokenizer.kind)
    with pytest.raises(ValueError, match=rf"kind.json: a '{tokenizer.kind}' tokenizer, not '{other}'"):
        kind_class(other).load(tmp_path)


def test_bits_per_chunk_are_tokens_times_log2_of_the_vocabulary(tokenizer, held_out_chunks):
    measured = measure_rate_distortion(tokenizer, held_out_chunks)
    lengths = tokenizer.encode(held_out_chunks).lengths.double()
    assert measured.tokens_mean == pytest.approx(float(lengths.mean()))
    assert measured.bits_per_chunk == pytest.approx(float(lengths.mean()) * math.log2(tokenizer.vocabulary_size))
    assert 0 <= measured.entropy_bits_per_chunk <= measured.bits_per_chunk + 1e-9
    assert len(measured.rmse_percent_range) == A and measured.invalid_rate == 0.0


def test_rows_that_cannot_form_a_chunk_are_repaired_and_counted(tokenizer, held_out_chunks):
    tokens = tokenizer.encode(held_out_chunks[:3])
    ids, lengths = tokens.ids.clone(), tokens.lengths.clone()
    ids[0, 0] = tokenizer.vocabulary_size  # outside the vocabulary
    lengths[1] -= 1  # one token short
    ids[1, lengths[1]] = PADDING_ID
    decoded = tokenizer.decode(TokenBatch(ids, lengths))
    assert decoded.actions.shape == (3, H, A) and torch.isfinite(decoded.actions).all()
    assert decoded.invalid.tolist() == [True, True, False]
