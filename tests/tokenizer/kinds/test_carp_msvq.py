"""The default kind is CARP's tokenizer unchanged: the same tokens, chunks and artifact as the module itself."""

import pytest
import torch

from carp.data.normalizer import MinMaxNormalizer
from carp.tokenizer.artifact import METADATA_FILENAME, WEIGHTS_FILENAME, save_tokenizer_artifact
from carp.tokenizer.kinds.base import TokenBatch
from carp.tokenizer.kinds.carp_msvq import CarpMsvqTokenizer
from carp.tokenizer.kinds.registry import load_tokenizer
from tests.tokenizer.kinds.conftest import build


@pytest.fixture
def wrapped() -> CarpMsvqTokenizer:
    return build("carp_msvq")


def test_tokens_and_chunks_are_the_modules_own_bit_for_bit(wrapped, held_out_chunks):
    module = wrapped.module
    with torch.no_grad():
        sequence = module.encode_to_sequence(held_out_chunks)
        chunks = module.decode_ids(module.encode_to_ids(held_out_chunks))
    tokens = wrapped.encode(held_out_chunks)
    assert torch.equal(tokens.ids, sequence)
    assert torch.equal(wrapped.decode(tokens).actions, chunks)
    assert wrapped.vocabulary_size == module.spec.codebook_size
    assert wrapped.tokens_per_chunk.maximum == module.spec.tokens_per_chunk


def test_the_pipelines_artifact_loads_as_carp_msvq_and_stays_byte_for_byte_the_same(wrapped, held_out_chunks, tmp_path):
    normalizers = {"lift": MinMaxNormalizer.fit(held_out_chunks.reshape(-1, 3).double().numpy())}
    first, second = tmp_path / "first", tmp_path / "second"
    save_tokenizer_artifact(first, wrapped.module, normalizers, "test-space")
    loaded = load_tokenizer(first)
    assert isinstance(loaded, CarpMsvqTokenizer)
    assert torch.equal(loaded.encode(held_out_chunks).ids, wrapped.encode(held_out_chunks).ids)
    # Loading through the seam leaves the artifact as the stage writes it: saving the loaded module again gives the
    # same metadata and the same weights.
    save_tokenizer_artifact(second, loaded.module, normalizers, "test-space")
    assert (first / METADATA_FILENAME).read_bytes() == (second / METADATA_FILENAME).read_bytes()
    first_state = torch.load(first / WEIGHTS_FILENAME, weights_only=True)["state_dict"]
    second_state = torch.load(second / WEIGHTS_FILENAME, weights_only=True)["state_dict"]
    assert first_state.keys() == second_state.keys()
    assert all(torch.equal(first_state[name], second_state[name]) for name in first_state)


def test_the_stage_trains_it_not_fit(wrapped, held_out_chunks):
    with pytest.raises(RuntimeError, match="carp.training.tokenizer_trainer"):
        wrapped.fit(held_out_chunks)


def test_a_row_of_the_wrong_length_is_flagged(wrapped, held_out_chunks):
    tokens = wrapped.encode(held_out_chunks[:2])
    short = TokenBatch(tokens.ids[:, :-1], tokens.lengths - 1)
    assert wrapped.decode(short).invalid.tolist() == [True, True]
