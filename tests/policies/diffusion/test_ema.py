import pytest
import torch
from torch import nn

from carp.policies.diffusion.config import DiffusionUNetConfig
from carp.policies.diffusion.ema import exponential_moving_average, warmup_decay
from carp.policies.diffusion.unet import ConditionalUNet1D


def test_decay_warms_up_and_is_capped():
    assert warmup_decay(1, 0.75, 0.9999) == 0.0
    assert warmup_decay(2, 0.75, 0.9999) == pytest.approx(1 - 2**-0.75)
    assert warmup_decay(10**9, 0.75, 0.9999) == 0.9999
    assert warmup_decay(100, 0.75, 0.5) == 0.5


def test_average_follows_diffusion_policys_update_sequence():
    model = nn.Linear(1, 1, bias=False)
    average = exponential_moving_average(model, power=0.75, max_decay=0.9999)
    values = [1.0, 2.0, 3.0, 5.0]
    for value in values:
        model.weight.data.fill_(value)
        average.update_parameters(model)
    # First update copies, second uses decay 0, then 1 - n ** -0.75 after n averaged updates.
    expected = 2.0
    for num_averaged, value in ((2, 3.0), (3, 5.0)):
        decay = 1 - num_averaged**-0.75
        expected = decay * expected + (1 - decay) * value
    assert average.module.weight.item() == pytest.approx(expected, rel=1e-6)
    assert int(average.n_averaged) == len(values)
    assert model.weight.item() == 5.0


def test_average_is_a_separate_copy_of_the_model():
    model = nn.Linear(2, 2)
    average = exponential_moving_average(model)
    model.weight.data.add_(1.0)
    assert not torch.equal(average.module.weight, model.weight)


def test_restored_average_resumes_its_warmup():
    model = nn.Linear(1, 1, bias=False)
    average = exponential_moving_average(model)
    for value in (1.0, 2.0, 3.0):
        model.weight.data.fill_(value)
        average.update_parameters(model)
    restored = exponential_moving_average(model)
    restored.load_state_dict(average.state_dict())
    model.weight.data.fill_(7.0)
    average.update_parameters(model)
    restored.update_parameters(model)
    assert restored.module.weight.item() == pytest.approx(average.module.weight.item())
    assert restored.module.weight.item() != pytest.approx(7.0)


def test_averaged_unet_uses_its_own_blocks():
    unet = ConditionalUNet1D(DiffusionUNetConfig(down_dims=(8, 16), num_groups=4, step_embedding_dim=8), 2, 3, 2)
    average = exponential_moving_average(unet)
    average.update_parameters(unet)
    copy = average.module
    assert copy._film_blocks[0] is copy.down_levels[0].first
    unet.down_levels[0].first.film.bias.data.add_(5.0)
    noisy, steps, obs = torch.randn(1, 4, 2), torch.tensor([3]), torch.randn(1, 2, 3)
    with torch.no_grad():
        assert not torch.allclose(copy(noisy, steps, obs), unet(noisy, steps, obs))
