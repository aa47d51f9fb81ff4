import math

import pytest
import torch
import torch.nn.functional as F

from carp.policies.carp.blocks import KeyValueCache
from carp.policies.carp.transformer import CoarseToFineTransformer
from tests.policies.carp.factories import OBS_DIM, OBS_STEPS, scrambled_transformer, tiny_policy_spec

SCALES = (1, 2, 3)
A, C, V = 2, 4, 8


def _inputs(batch: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    obs = torch.randn(batch, OBS_STEPS, OBS_DIM, generator=generator)
    teacher = torch.randn(batch, A * sum(SCALES[1:]), C, generator=generator)  # (B, L - s_1 * A, C)
    return obs, teacher


def test_default_initialization_gives_near_uniform_logits():
    torch.manual_seed(0)
    transformer = CoarseToFineTransformer(tiny_policy_spec(SCALES))
    obs, teacher = _inputs(4)
    logits = transformer(obs, teacher)
    assert logits.shape == (4, A * sum(SCALES), V)
    loss = F.cross_entropy(logits.reshape(-1, V), torch.zeros(logits.shape[0] * logits.shape[1], dtype=torch.long))
    assert loss.item() == pytest.approx(math.log(V), abs=0.02)


def test_logits_of_coarser_scales_ignore_finer_inputs():
    transformer = scrambled_transformer(tiny_policy_spec(SCALES))
    obs, teacher = _inputs(3)
    reference = transformer(obs, teacher)
    # Teacher inputs hold scale 2 at [0, 4) and scale 3 at [4, 10); the sequence holds scales 1..3 at [0, 2, 6, 12).
    changed_scale_3 = teacher.clone()
    changed_scale_3[:, 4:] += 1.0
    logits = transformer(obs, changed_scale_3)
    torch.testing.assert_close(logits[:, :6], reference[:, :6], rtol=0, atol=1e-6)
    assert (logits[:, 6:] - reference[:, 6:]).abs().max() > 1e-2

    changed_scale_2 = teacher.clone()
    changed_scale_2[:, :4] += 1.0
    logits = transformer(obs, changed_scale_2)
    torch.testing.assert_close(logits[:, :2], reference[:, :2], rtol=0, atol=1e-6)
    assert (logits[:, 2:6] - reference[:, 2:6]).abs().max() > 1e-2


def test_tokens_of_one_scale_see_each_other():
    transformer = scrambled_transformer(tiny_policy_spec(SCALES))
    obs, teacher = _inputs(1)
    reference = transformer(obs, teacher)
    changed = teacher.clone()
    changed[:, 3] += 1.0  # last token of scale 2 changes the first token of scale 2 (bidirectional within a scale)
    assert (transformer(obs, changed)[:, 2] - reference[:, 2]).abs().max() > 1e-2


def test_head_scores_token_i_with_dimension_i_mod_a():
    transformer = scrambled_transformer(tiny_policy_spec(SCALES))
    with torch.no_grad():
        transformer.head.weight[1].zero_()
        transformer.head.bias[1].fill_(7.0)
    logits = transformer(*_inputs(2))
    assert torch.all(logits[:, 1::2] == 7.0)
    assert (logits[:, 0::2] - 7.0).abs().min() > 0


def test_grouped_logits_are_the_same_logits_in_the_heads_layout():
    transformer = scrambled_transformer(tiny_policy_spec(SCALES))
    inputs = _inputs(3)
    logits = transformer(*inputs)  # (B, L, V)
    grouped = transformer(*inputs, grouped_by_dimension=True)  # (A, B * L / A, V)
    assert grouped.shape == (A, 3 * A * sum(SCALES) // A, V)
    torch.testing.assert_close(transformer.head.ungroup(grouped, 3), logits, rtol=0, atol=0)
    # Group `a` holds dimension a's tokens (sequence positions a, a + A, ...) of sample 0, then sample 1, ...
    tokens_per_sample = sum(SCALES)
    torch.testing.assert_close(grouped[1, :tokens_per_sample], logits[0, 1::A], rtol=0, atol=0)
    torch.testing.assert_close(grouped[0, tokens_per_sample : 2 * tokens_per_sample], logits[1, 0::A], rtol=0, atol=0)
    ids = torch.arange(3 * A * tokens_per_sample).view(3, -1)  # (B, L)
    assert torch.equal(transformer.head.ungroup(transformer.head.group(ids), 3), ids)
    assert torch.equal(transformer.head.group(ids)[1, :tokens_per_sample], ids[0, 1::A])


def test_kv_cache_logits_equal_full_forward():
    transformer = scrambled_transformer(tiny_policy_spec(SCALES))
    obs, teacher = _inputs(3)
    reference = transformer(obs, teacher)
    with torch.inference_mode():
        state = transformer.start_inference(obs)
        cached = [transformer.next_scale_logits(state)]
        cached.append(transformer.next_scale_logits(state, teacher[:, :4]))
        cached.append(transformer.next_scale_logits(state, teacher[:, 4:]))
        with pytest.raises(RuntimeError, match="all 3 scales were already predicted"):
            transformer.next_scale_logits(state, teacher[:, 4:])
    torch.testing.assert_close(torch.cat(cached, dim=1), reference, rtol=1e-5, atol=1e-5)


def test_later_scales_require_inputs():
    transformer = scrambled_transformer(tiny_policy_spec(SCALES))
    with torch.inference_mode():
        state = transformer.start_inference(_inputs(1)[0])
        transformer.next_scale_logits(state)
        with pytest.raises(ValueError, match="scale 2 needs the accumulated latent"):
            transformer.next_scale_logits(state)


def test_bad_condition_inputs_are_rejected():
    transformer = scrambled_transformer(tiny_policy_spec(SCALES))
    obs, teacher = _inputs(2)
    with pytest.raises(ValueError, match="expected To \\* Do = 2 \\* 3 = 6"):
        transformer(obs[:, :1], teacher)


def test_gradients_reach_every_parameter():
    transformer = scrambled_transformer(tiny_policy_spec(SCALES)).train()
    obs, teacher = _inputs(2)
    transformer(obs, teacher).logsumexp(-1).sum().backward()
    missing = [name for name, parameter in transformer.named_parameters() if parameter.grad is None]
    assert missing == []


def test_kv_cache_rejects_more_tokens_than_its_capacity():
    cache = KeyValueCache(depth=1, capacity=3)
    cache.extend(0, torch.zeros(1, 2, 2, 1, 4))
    with pytest.raises(RuntimeError, match="capacity 3 cannot hold 4 tokens"):
        cache.extend(0, torch.zeros(1, 2, 2, 1, 4))
