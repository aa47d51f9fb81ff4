import pytest
import torch

from carp.policies.diffusion.config import DiffusionTransformerConfig
from carp.policies.diffusion.transformer import DiffusionTransformer

CAN_OBS_DIM, OBS_STEPS, ACTION_DIM = 23, 2, 10
TINY = DiffusionTransformerConfig(num_layers=2, num_heads=2, width=16, attention_dropout=0.0)
HORIZON = 6


def _count(model: torch.nn.Module) -> int:
    return sum(parameter.numel() for parameter in model.parameters())


def _tiny_transformer(seed: int = 0) -> DiffusionTransformer:
    torch.manual_seed(seed)
    transformer = DiffusionTransformer(TINY, action_dim=3, obs_dim=4, obs_steps=OBS_STEPS, action_horizon=HORIZON)
    for parameter in transformer.parameters():  # larger weights so that every path visibly matters
        parameter.data.normal_(0.0, 0.3)
    return transformer.eval()


def test_paper_size_has_9_0_million_parameters_at_horizon_10():
    at_10 = DiffusionTransformer(DiffusionTransformerConfig(), ACTION_DIM, CAN_OBS_DIM, OBS_STEPS, 10)
    at_16 = DiffusionTransformer(DiffusionTransformerConfig(), ACTION_DIM, CAN_OBS_DIM, OBS_STEPS, 16)
    assert _count(at_10) == pytest.approx(9.0e6, rel=0.01)
    # The counts stated in DiffusionTransformerConfig's docstring; H = 16 adds one 256-wide position row per action.
    assert (_count(at_10), _count(at_16)) == (8_968_458, 8_969_994)


def test_output_has_the_shape_of_the_noisy_actions():
    transformer = _tiny_transformer()
    noisy = torch.randn(4, HORIZON, 3)
    with torch.no_grad():
        noise = transformer(noisy, torch.tensor([0, 1, 50, 99]), torch.randn(4, OBS_STEPS, 4))
    assert noise.shape == noisy.shape


def test_other_horizons_are_refused():
    with pytest.raises(ValueError, match="denoises H=6 actions, got H=8"):
        _tiny_transformer()(torch.randn(1, 8, 3), torch.tensor([0]), torch.randn(1, OBS_STEPS, 4))


def test_self_attention_is_causal_over_action_tokens():
    transformer = _tiny_transformer()
    obs, noisy = torch.randn(2, OBS_STEPS, 4), torch.randn(2, HORIZON, 3)
    steps = torch.tensor([5, 60])
    with torch.no_grad():
        reference = transformer(noisy, steps, obs)
        changed = noisy.clone()
        changed[:, 3] += 1.0
        result = transformer(changed, steps, obs)
    torch.testing.assert_close(result[:, :3], reference[:, :3], rtol=0, atol=1e-6)
    assert (result[:, 3:] - reference[:, 3:]).abs().amax(dim=(0, 2)).min() > 1e-4


def test_action_token_t_sees_observation_steps_up_to_t_as_diffusion_policy_masks_them():
    transformer = _tiny_transformer()
    obs, noisy = torch.randn(2, OBS_STEPS, 4), torch.randn(2, HORIZON, 3)
    steps = torch.tensor([5, 60])
    with torch.no_grad():
        reference = transformer(noisy, steps, obs)
        changed = obs.clone()
        changed[:, 1] += 1.0  # the second observation step: memory token 2
        result = transformer(noisy, steps, changed)
    torch.testing.assert_close(result[:, 0], reference[:, 0], rtol=0, atol=1e-6)
    assert (result[:, 1:] - reference[:, 1:]).abs().amax(dim=(0, 2)).min() > 1e-4


def test_prepared_inference_equals_the_training_forward():
    transformer = _tiny_transformer()
    obs, noisy = torch.randn(3, OBS_STEPS, 4), torch.randn(3, HORIZON, 3)
    steps = torch.tensor([99, 42, 0])
    with torch.no_grad():
        condition = transformer.prepare(obs, steps, HORIZON)
        for index, step in enumerate(steps):
            prepared = transformer.predict_noise(noisy, condition, index)
            direct = transformer(noisy, step.repeat(3), obs)
            torch.testing.assert_close(prepared, direct, rtol=1e-4, atol=1e-5)


def test_parameter_groups_split_every_parameter_once():
    transformer = _tiny_transformer()
    decay, no_decay = transformer.parameter_groups(1e-3)
    assert (decay["weight_decay"], no_decay["weight_decay"]) == (1e-3, 0.0)
    grouped = [id(parameter) for group in (decay, no_decay) for parameter in group["params"]]
    assert sorted(grouped) == sorted(id(parameter) for parameter in transformer.parameters())
    assert all(parameter.dim() == 2 for parameter in decay["params"])
    no_decay_ids = {id(parameter) for parameter in no_decay["params"]}
    assert {id(transformer.action_position), id(transformer.final_norm.weight)} <= no_decay_ids
