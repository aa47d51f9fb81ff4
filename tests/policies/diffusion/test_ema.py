import pytest
import torch
from torch import nn

from carp.policies.diffusion.ema import exponential_moving_average, warmup_decay


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
