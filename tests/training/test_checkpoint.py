import random

import numpy as np
import pytest
import torch
from torch import nn

from carp.training.checkpoint import (
    CheckpointFormatError,
    atomic_torch_save,
    load_training_state,
    read_training_metadata,
    save_training_state,
)


def make_run(seed: int = 0):
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)
    model = nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 1))
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-2, weight_decay=0.01)
    scheduler = torch.optim.lr_scheduler.StepLR(optimizer, step_size=2, gamma=0.5)
    return model, optimizer, scheduler


def train_epoch(model, optimizer, scheduler):
    # Draws from the global torch, numpy and Python generators, so resuming is exact only if all three are restored.
    inputs = torch.randn(16, 3) + float(np.random.uniform(-0.1, 0.1)) + random.uniform(-0.1, 0.1)
    targets = inputs.sum(dim=1, keepdim=True)
    for batch in range(4):
        loss = (model(inputs[batch * 4 : (batch + 1) * 4]) - targets[batch * 4 : (batch + 1) * 4]).pow(2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    scheduler.step()


def test_round_trip_restores_every_part(tmp_path):
    model, optimizer, scheduler = make_run()
    train_epoch(model, optimizer, scheduler)
    path = tmp_path / "state.pt"
    save_training_state(path, model, optimizer, scheduler, epoch=1, metadata={"width": 8})
    expected_draw = torch.rand(3), np.random.rand(), random.random()

    restored_model, restored_optimizer, restored_scheduler = make_run(seed=1)
    assert load_training_state(path, restored_model, restored_optimizer, restored_scheduler) == 1
    for expected, actual in zip(model.state_dict().values(), restored_model.state_dict().values(), strict=True):
        assert torch.equal(expected, actual)
    expected_moments = optimizer.state_dict()["state"][0]["exp_avg"]
    assert torch.equal(restored_optimizer.state_dict()["state"][0]["exp_avg"], expected_moments)
    assert restored_scheduler.state_dict() == scheduler.state_dict()
    torch_draw, numpy_draw, python_draw = torch.rand(3), np.random.rand(), random.random()
    assert torch.equal(torch_draw, expected_draw[0])
    assert numpy_draw == expected_draw[1] and python_draw == expected_draw[2]
    assert read_training_metadata(path) == {"width": 8}
    assert [p.name for p in tmp_path.iterdir()] == ["state.pt"], "no temporary files may be left behind"


def test_resume_matches_an_uninterrupted_run(tmp_path):
    model, optimizer, scheduler = make_run()
    for _ in range(4):
        train_epoch(model, optimizer, scheduler)

    interrupted = make_run()
    for _ in range(2):
        train_epoch(*interrupted)
    save_training_state(tmp_path / "state.pt", *interrupted, epoch=2)
    resumed = make_run(seed=7)
    torch.rand(5)  # a fresh process would have consumed randomness differently
    start = load_training_state(tmp_path / "state.pt", *resumed)
    for _ in range(start, 4):
        train_epoch(*resumed)
    for expected, actual in zip(model.state_dict().values(), resumed[0].state_dict().values(), strict=True):
        assert torch.equal(expected, actual)


def test_format_version_mismatch_is_a_clear_error(tmp_path):
    path = tmp_path / "old.pt"
    torch.save({"format_version": 0, "epoch": 3}, path)
    model, optimizer, scheduler = make_run()
    with pytest.raises(CheckpointFormatError, match=r"format_version 0, this code reads version 1"):
        load_training_state(path, model, optimizer, scheduler)
    torch.save({"weights": 1}, path)
    with pytest.raises(CheckpointFormatError, match=r"format_version None"):
        read_training_metadata(path)


def test_loading_is_strict(tmp_path):
    model, optimizer, scheduler = make_run()
    save_training_state(tmp_path / "state.pt", model, optimizer, scheduler, epoch=0)
    other = nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 1), nn.Linear(1, 1))
    other_optimizer = torch.optim.AdamW(other.parameters())
    with pytest.raises(RuntimeError, match="Unexpected key|Missing key"):
        load_training_state(tmp_path / "state.pt", other, other_optimizer, None)


def test_atomic_save_replaces_existing_file(tmp_path):
    path = tmp_path / "nested" / "payload.pt"
    atomic_torch_save({"value": 1}, path)
    atomic_torch_save({"value": 2}, path)
    assert torch.load(path)["value"] == 2
    assert sorted(p.name for p in path.parent.iterdir()) == ["payload.pt"]
