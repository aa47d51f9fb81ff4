import pytest
import torch

from carp.policies.carp.sampling import generate_chunk, select_tokens
from tests.policies.carp.factories import OBS_DIM, OBS_STEPS, scrambled_transformer, tiny_policy_spec, tiny_tokenizer

SCALES = (1, 2, 3)


def _setup(batch: int = 5, seed: int = 0):
    tokenizer = tiny_tokenizer(SCALES, seed)
    transformer = scrambled_transformer(tiny_policy_spec(SCALES), seed)
    obs = torch.randn(batch, OBS_STEPS, OBS_DIM, generator=torch.Generator().manual_seed(seed))
    return tokenizer, transformer, obs


def test_greedy_inference_equals_argmax_of_teacher_forced_forward():
    tokenizer, transformer, obs = _setup()
    with torch.inference_mode():
        chunk = generate_chunk(transformer, tokenizer, obs)
        sequence = tokenizer.ids_to_sequence(chunk.token_ids)  # (B, L)
        logits = transformer(obs, tokenizer.teacher_forcing_sequence(chunk.token_ids))
        assert torch.equal(logits.argmax(dim=-1), sequence)
        torch.testing.assert_close(chunk.latent, tokenizer.ids_to_latent(chunk.token_ids))
    assert [tuple(ids.shape) for ids in chunk.token_ids] == [(5, 2, 1), (5, 2, 2), (5, 2, 3)]
    # The scrambled model does not collapse onto one token, so the equality above is informative.
    assert sequence.unique().numel() > 3


def test_batch_gives_the_same_tokens_as_one_by_one():
    tokenizer, transformer, obs = _setup(batch=4)
    with torch.inference_mode():
        batched = generate_chunk(transformer, tokenizer, obs)
        for index in range(4):
            single = generate_chunk(transformer, tokenizer, obs[index : index + 1])
            for scale_ids, single_ids in zip(batched.token_ids, single.token_ids, strict=True):
                assert torch.equal(scale_ids[index : index + 1], single_ids)
            torch.testing.assert_close(batched.latent[index : index + 1], single.latent, rtol=1e-5, atol=1e-6)


def test_top_k_sampling_is_reproducible_with_a_seeded_generator():
    tokenizer, transformer, obs = _setup(batch=16)

    def sample(seed: int) -> torch.Tensor:
        with torch.inference_mode():
            chunk = generate_chunk(transformer, tokenizer, obs, top_k=4, generator=torch.Generator().manual_seed(seed))
        return tokenizer.ids_to_sequence(chunk.token_ids)

    assert torch.equal(sample(1), sample(1))
    assert not torch.equal(sample(1), sample(2))


def test_top_1_sampling_equals_greedy():
    tokenizer, transformer, obs = _setup()
    with torch.inference_mode():
        greedy = generate_chunk(transformer, tokenizer, obs)
        top_one = generate_chunk(transformer, tokenizer, obs, top_k=1, generator=torch.Generator().manual_seed(3))
    for greedy_ids, top_one_ids in zip(greedy.token_ids, top_one.token_ids, strict=True):
        assert torch.equal(greedy_ids, top_one_ids)


def test_select_tokens_draws_only_from_the_top_k():
    logits = torch.tensor([[[0.0, 5.0, 4.0, -1.0, 3.0]]]).expand(1, 2000, 5)
    drawn = select_tokens(logits, top_k=2, generator=torch.Generator().manual_seed(0))
    assert set(drawn.unique().tolist()) == {1, 2}
    # Softmax over the two kept logits: p(1) = 1 / (1 + e^-1) ~ 0.731.
    assert (drawn == 1).float().mean().item() == pytest.approx(0.731, abs=0.03)
    assert torch.equal(select_tokens(logits, top_k=1), torch.ones(1, 2000, dtype=torch.long))


def test_given_uniforms_decide_the_draw_and_must_fit_the_logits():
    logits = torch.tensor([[[0.0, 5.0, 4.0, -1.0, 3.0]]])  # top-2: ids 1 (5.0), 2 (4.0)
    # Gumbel offsets -log(-log(u)): u = 0.5 -> 0.37, u = 0.99 -> 4.6, so the second candidate wins only with 0.99.
    assert select_tokens(logits, top_k=2, uniforms=torch.tensor([[[0.5, 0.5]]])).item() == 1
    assert select_tokens(logits, top_k=2, uniforms=torch.tensor([[[0.5, 0.99]]])).item() == 2
    with pytest.raises(ValueError, match=r"uniforms must have shape \(1, 1, 2\), got \(1, 1, 3\)"):
        select_tokens(logits, top_k=2, uniforms=torch.rand(1, 1, 3))


@pytest.mark.parametrize("top_k", [0, 6, 2.0, True])
def test_select_tokens_rejects_bad_top_k(top_k):
    with pytest.raises(ValueError, match="top_k must be an integer in \\[1, V = 5\\]"):
        select_tokens(torch.zeros(1, 3, 5), top_k=top_k)
