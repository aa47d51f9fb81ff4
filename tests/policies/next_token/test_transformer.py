import math

import pytest
import torch
import torch.nn.functional as F

from carp.config import ConfigError
from carp.policies.carp.transformer import CoarseToFineTransformer
from carp.policies.next_token.config import NextTokenConfig, NextTokenInference
from carp.policies.next_token.generation import check_tokenizer_matches, generate_tokens
from carp.policies.next_token.transformer import NextTokenTransformer
from tests.policies.carp.factories import OBS_DIM, OBS_STEPS, tiny_policy_spec, tiny_tokenizer

SCALES = (1, 2, 3)
A, V = 2, 8
L = A * sum(SCALES)
TINY = NextTokenConfig(depth=2, width=16, num_heads=2)


def _model(scrambled: bool = True, seed: int = 0) -> NextTokenTransformer:
    torch.manual_seed(seed)
    model = NextTokenTransformer(TINY, OBS_DIM, OBS_STEPS, A, SCALES, V)
    if scrambled:  # the default initialization is near-identity with near-uniform logits: equivalences would be trivial
        with torch.no_grad():
            for parameter in model.parameters():
                parameter.normal_(0.0, 0.3)
    return model.eval()


def _obs(batch: int, seed: int = 0) -> torch.Tensor:
    return torch.randn(batch, OBS_STEPS, OBS_DIM, generator=torch.Generator().manual_seed(seed))


def test_default_initialization_gives_near_uniform_logits():
    model = _model(scrambled=False)
    token_ids = torch.randint(0, V, (4, L))
    logits = model(_obs(4), token_ids)
    assert logits.shape == (4, L, V)
    assert F.cross_entropy(logits.reshape(-1, V), token_ids.reshape(-1)).item() == pytest.approx(math.log(V), abs=0.02)


def test_cached_greedy_generation_equals_the_argmax_of_a_teacher_forced_forward_at_every_position():
    model = _model()
    obs = _obs(3)
    state = model.start_inference(obs)
    previous, generated, stepwise_logits = None, [], []
    with torch.inference_mode():
        for _ in range(L):
            logits = model.next_token_logits(state, previous)  # (B, V)
            previous = logits.argmax(dim=-1)
            generated.append(previous)
            stepwise_logits.append(logits)
    generated = torch.stack(generated, dim=1)  # (B, L)
    assert torch.equal(generated, generate_tokens(model, obs))
    with torch.no_grad():
        full = model(obs, generated)  # (B, L, V)
    torch.testing.assert_close(torch.stack(stepwise_logits, dim=1), full, rtol=1e-4, atol=1e-4)
    assert torch.equal(full.argmax(dim=-1), generated)
    # The scrambled model does not choose one token everywhere: the check covers real choices.
    assert generated.unique().numel() > 2


def test_mask_is_causal_a_later_token_never_changes_earlier_logits():
    model = _model()
    obs = _obs(2)
    token_ids = torch.randint(0, V, (2, L), generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        reference = model(obs, token_ids)
        for position in (0, 5, L - 2):
            changed = token_ids.clone()
            changed[:, position] = (changed[:, position] + 1) % V
            logits = model(obs, changed)
            # Logits at i read tokens < i, so those up to `position` are unchanged and the next one changes.
            torch.testing.assert_close(logits[:, : position + 1], reference[:, : position + 1], rtol=0, atol=1e-6)
            assert (logits[:, position + 1] - reference[:, position + 1]).abs().max() > 1e-3


def test_last_token_is_never_read():
    model = _model()
    token_ids = torch.randint(0, V, (2, L))
    changed = token_ids.clone()
    changed[:, -1] = (changed[:, -1] + 3) % V
    with torch.no_grad():
        torch.testing.assert_close(model(_obs(2), changed), model(_obs(2), token_ids), rtol=0, atol=0)


def test_top_k_generation_is_seeded_and_stays_within_the_k_best_tokens():
    model = _model()
    obs = _obs(4)
    first = generate_tokens(model, obs, top_k=3, generator=torch.Generator().manual_seed(5))
    second = generate_tokens(model, obs, top_k=3, generator=torch.Generator().manual_seed(5))
    assert torch.equal(first, second)
    with torch.no_grad():
        top_three = model(obs, first).topk(3, dim=-1).indices  # (B, L, 3)
    assert (top_three == first.unsqueeze(-1)).any(dim=-1).all()
    greedy = generate_tokens(model, obs)
    assert not torch.equal(first, greedy)


def test_generation_past_the_last_token_is_refused():
    model = _model()
    state = model.start_inference(_obs(1))
    previous = None
    with torch.inference_mode():
        for _ in range(L):
            previous = model.next_token_logits(state, previous).argmax(dim=-1)
        with pytest.raises(RuntimeError, match=f"all {L} tokens"):
            model.next_token_logits(state, previous)


def test_generated_tokens_decode_to_an_action_chunk_with_the_tokenizer():
    tokenizer, model = tiny_tokenizer(SCALES), _model()
    check_tokenizer_matches(model, tokenizer)
    token_ids = generate_tokens(model, _obs(2))  # (B, L)
    actions = tokenizer.decode_ids(tokenizer.sequence_to_ids(token_ids))
    assert actions.shape == (2, tokenizer.spec.action_horizon, A)
    assert torch.isfinite(actions).all()
    with pytest.raises(ValueError, match=r"scales: model \(1, 2, 3\) vs tokenizer \(1, 2\)"):
        check_tokenizer_matches(model, tiny_tokenizer((1, 2)))


def test_transformer_blocks_are_the_size_of_carps():
    model = _model(scrambled=False)
    carp = CoarseToFineTransformer(tiny_policy_spec(SCALES, depth=TINY.depth, width=TINY.width, num_heads=2))

    def count(module: torch.nn.Module) -> int:
        return sum(parameter.numel() for parameter in module.parameters())

    for name in ("blocks", "modulation", "head", "condition_projection"):
        assert count(getattr(model, name)) == count(getattr(carp, name)), name
    assert model.position_embedding.shape == carp.position_embedding.shape


def test_bad_config_values_are_refused_with_the_dotted_key():
    with pytest.raises(ConfigError, match=r"^next_token.num_heads=3: must divide width=64"):
        NextTokenConfig(num_heads=3)
    with pytest.raises(ConfigError, match=r"^inference.next_token.top_k=0: must be an integer >= 1"):
        NextTokenInference(top_k=0)
    with pytest.raises(ConfigError, match=r"^next_token.dropout=1.0: must be in \[0, 1\)"):
        NextTokenConfig(dropout=1.0)
