import torch
from einops import rearrange

from carp.policies.carp.layout import TokenLayout


def test_bounds_levels_and_dimensions():
    layout = TokenLayout(action_dim=3, scales=(1, 2, 4))
    assert layout.scale_lengths == (3, 6, 12)
    assert layout.sequence_length == 21
    assert layout.scale_bounds == ((0, 3), (3, 9), (9, 21))
    assert layout.level_ids().tolist() == [0] * 3 + [1] * 6 + [2] * 12
    assert layout.dimension_ids().tolist() == [0, 1, 2] * 7


def test_mask_is_block_causal():
    layout = TokenLayout(action_dim=2, scales=(1, 2, 3))
    mask = layout.attention_mask()
    levels = layout.level_ids()
    assert mask.shape == (12, 12) and mask.dtype == torch.bool
    for query in range(12):
        for key in range(12):
            assert bool(mask[query, key]) == bool(levels[key] <= levels[query])
    # Tokens of one scale see each other, including later positions of the same scale.
    assert bool(mask[2, 5]) and not bool(mask[2, 6])


def test_scale_reordering_matches_sequence_layout():
    layout = TokenLayout(action_dim=3, scales=(2,))
    ids = torch.tensor([[[10, 11], [20, 21], [30, 31]]])  # (B, A, s): dimension d, position p -> 10 * (d + 1) + p
    sequence = torch.tensor([[10, 20, 30, 11, 21, 31]])  # pos0: d0 d1 d2, pos1: d0 d1 d2
    assert torch.equal(layout.scale_tokens_to_ids(sequence), ids)
    latent = ids.unsqueeze(2).expand(-1, -1, 4, -1).float()  # (B, A, C, s)
    tokens = layout.scale_inputs_to_tokens(latent)
    assert torch.equal(tokens[0, :, 0], sequence[0].float())


def test_view_based_reordering_equals_the_einops_patterns():
    layout = TokenLayout(action_dim=3, scales=(1, 4))
    tokens = torch.randint(0, 100, (2, 12))
    assert torch.equal(layout.scale_tokens_to_ids(tokens), rearrange(tokens, "b (s a) -> b a s", a=3))
    inputs = torch.randn(2, 3, 5, 4)
    assert torch.equal(layout.scale_inputs_to_tokens(inputs), rearrange(inputs, "b a c s -> b (s a) c"))
