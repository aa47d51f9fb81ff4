import logging
import random

import numpy as np
import pytest
import torch
from torch import nn

from carp.training.checkpoint import (
    TRAINING_STATE_FORMAT_VERSION,
    CheckpointError,
    CheckpointFormatError,
    atomic_torch_save,
    read_checkpoint,
    read_training_state,
    resume_training_state,
    save_training_state,
)

METADATA = {"width": 8}


def make_run(seed: int = 0):
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)
    model = nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 1))
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-2, weight_decay=0.01)
    scheduler = torch.optim.lr_scheduler.StepLR(optimizer, step_size=2, gamma=0.5)
    return model, optimizer, scheduler


def train_epoch(model, optimizer, scheduler) -> dict[str, float]:
    # Draws from the global torch, numpy and Python generators, so resuming is exact only if all three are restored.
    inputs = torch.randn(16, 3) + float(np.random.uniform(-0.1, 0.1)) + random.uniform(-0.1, 0.1)
    targets = inputs.sum(dim=1, keepdim=True)
    for batch in range(4):
        loss = (model(inputs[batch * 4 : (batch + 1) * 4]) - targets[batch * 4 : (batch + 1) * 4]).pow(2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    scheduler.step()
    return {"loss": float(loss.detach())}


def weights(model: nn.Module) -> dict[str, torch.Tensor]:
    return {name: value.detach().clone() for name, value in model.state_dict().items()}


def saved_state(path, epochs: int = 1):
    """A training state after `epochs` epochs, and the run that wrote it."""
    run = make_run()
    history = [train_epoch(*run) for _ in range(epochs)]
    save_training_state(path, *run, epoch=epochs, metadata=METADATA, history=history)
    return run, history


def test_round_trip_restores_every_part_and_reports_the_stored_epochs(tmp_path):
    path = tmp_path / "state.pt"
    (model, optimizer, scheduler), history = saved_state(path)
    expected_draw = torch.rand(3), np.random.rand(), random.random()

    restored_model, restored_optimizer, restored_scheduler = make_run(seed=1)
    reported = []
    start, restored_history = resume_training_state(
        path, METADATA, restored_model, restored_optimizer, restored_scheduler, lambda e, m: reported.append((e, m))
    )
    assert (start, restored_history) == (1, history) and reported == [(0, history[0])]
    for expected, actual in zip(model.state_dict().values(), restored_model.state_dict().values(), strict=True):
        assert torch.equal(expected, actual)
    expected_moments = optimizer.state_dict()["state"][0]["exp_avg"]
    assert torch.equal(restored_optimizer.state_dict()["state"][0]["exp_avg"], expected_moments)
    assert restored_scheduler.state_dict() == scheduler.state_dict()
    torch_draw, numpy_draw, python_draw = torch.rand(3), np.random.rand(), random.random()
    assert torch.equal(torch_draw, expected_draw[0])
    assert numpy_draw == expected_draw[1] and python_draw == expected_draw[2]
    assert read_training_state(path)["metadata"] == METADATA
    assert [p.name for p in tmp_path.iterdir()] == ["state.pt"], "no temporary files may be left behind"


def test_resume_matches_an_uninterrupted_run(tmp_path):
    model, optimizer, scheduler = make_run()
    for _ in range(4):
        train_epoch(model, optimizer, scheduler)

    interrupted = make_run()
    history = [train_epoch(*interrupted) for _ in range(2)]
    save_training_state(tmp_path / "state.pt", *interrupted, epoch=2, metadata=METADATA, history=history)
    resumed = make_run(seed=7)
    torch.rand(5)  # a fresh process would have consumed randomness differently
    start, _ = resume_training_state(tmp_path / "state.pt", METADATA, *resumed)
    for _ in range(start, 4):
        train_epoch(*resumed)
    for expected, actual in zip(model.state_dict().values(), resumed[0].state_dict().values(), strict=True):
        assert torch.equal(expected, actual)


def _truncate(path):
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _rewrite(change):
    def apply(path):
        payload = torch.load(path, weights_only=False)
        change(payload)
        torch.save(payload, path)

    return apply


UNUSABLE_STATES = {
    "truncated": (_truncate, "not a readable checkpoint, truncated or corrupt"),
    "empty": (lambda path: path.write_bytes(b""), "not a readable checkpoint, truncated or corrupt"),
    "garbage": (lambda path: path.write_bytes(b"not a checkpoint" * 8), "not a readable checkpoint"),
    "another format version": (
        _rewrite(lambda payload: payload.update(format_version=TRAINING_STATE_FORMAT_VERSION + 1)),
        f"format_version {TRAINING_STATE_FORMAT_VERSION + 1}, this code reads version",
    ),
    "no history": (_rewrite(lambda payload: payload.pop("history")), "training state lacks history"),
    "history of another length": (
        _rewrite(lambda payload: payload.update(history=[])),
        "after 1 epochs holds 0 epochs of history",
    ),
    "another model": (
        _rewrite(lambda payload: payload["model"].update({"3.weight": torch.zeros(1, 1)})),
        "model parameters do not fit this model (3.weight)",
    ),
}


@pytest.mark.parametrize("damage", list(UNUSABLE_STATES))
def test_an_unusable_state_is_discarded_with_one_warning_and_training_starts_over(tmp_path, caplog, damage):
    path = tmp_path / "state.pt"
    saved_state(path)
    change, reason = UNUSABLE_STATES[damage]
    change(path)
    model, optimizer, scheduler = make_run(seed=3)
    before, optimizer_before, draw_state = weights(model), optimizer.state_dict(), torch.get_rng_state()
    with caplog.at_level(logging.WARNING, logger="carp.training.checkpoint"):
        assert resume_training_state(path, METADATA, model, optimizer, scheduler) == (0, [])
    warnings = [record.getMessage() for record in caplog.records]
    assert len(warnings) == 1 and "\n" not in warnings[0], warnings
    assert warnings[0].startswith(f"discarding training state {path}: ") and reason in warnings[0], warnings
    assert warnings[0].endswith("training starts over")
    # Nothing was half-restored: the run starts exactly as a fresh one would.
    for name, value in weights(model).items():
        assert torch.equal(value, before[name]), name
    assert optimizer.state_dict() == optimizer_before and torch.equal(torch.get_rng_state(), draw_state)
    assert not path.exists()


def test_a_state_of_another_setup_is_ignored_and_kept_until_overwritten(tmp_path, caplog):
    path = tmp_path / "state.pt"
    saved_state(path)
    with caplog.at_level(logging.WARNING, logger="carp.training.checkpoint"):
        assert resume_training_state(path, {"width": 16}, *make_run()) == (0, [])
    assert f"ignoring {path}: it was written for another setup (different width)" in caplog.text
    assert path.exists()


def test_a_missing_state_starts_over_silently_and_leftover_temporaries_are_removed(tmp_path, caplog):
    path = tmp_path / "state.pt"
    # What a process killed inside atomic_torch_save leaves behind.
    leftover = tmp_path / ".state.pt.12345.tmp"
    leftover.write_bytes(b"half a checkpoint")
    other = tmp_path / ".other.pt.12345.tmp"
    other.write_bytes(b"not ours")
    with caplog.at_level(logging.WARNING):
        assert resume_training_state(path, METADATA, *make_run()) == (0, [])
    assert caplog.text == ""
    assert not leftover.exists() and other.exists()


def test_read_checkpoint_turns_a_damaged_file_into_one_line(tmp_path):
    path = tmp_path / "payload.pt"
    torch.save({"weights": torch.zeros(1000)}, path)
    _truncate(path)
    with pytest.raises(CheckpointError) as raised:
        read_checkpoint(path, weights_only=True)
    message = str(raised.value)
    assert message.startswith(f"{path}: not a readable checkpoint, truncated or corrupt (RuntimeError: ")
    assert "\n" not in message and "internal miniz error" not in message
    with pytest.raises(FileNotFoundError, match="missing.pt: file not found"):
        read_checkpoint(tmp_path / "missing.pt", weights_only=True)


def test_format_version_mismatch_is_a_clear_error(tmp_path):
    path = tmp_path / "old.pt"
    torch.save({"format_version": 0, "epoch": 3}, path)
    with pytest.raises(CheckpointFormatError, match=r"format_version 0, this code reads version 1"):
        read_training_state(path)
    torch.save({"weights": 1}, path)
    with pytest.raises(CheckpointFormatError, match=r"format_version None"):
        read_training_state(path)


def test_history_must_cover_the_saved_epochs(tmp_path):
    with pytest.raises(ValueError, match="after 2 epochs needs 2 epochs of history, got 1"):
        save_training_state(tmp_path / "state.pt", *make_run(), epoch=2, metadata=METADATA, history=[{"loss": 1.0}])


def test_atomic_save_replaces_existing_file(tmp_path):
    path = tmp_path / "nested" / "payload.pt"
    atomic_torch_save({"value": 1}, path)
    atomic_torch_save({"value": 2}, path)
    assert torch.load(path)["value"] == 2
    assert sorted(p.name for p in path.parent.iterdir()) == ["payload.pt"]


def test_atomic_save_writes_the_same_bytes_from_any_process_under_any_name(tmp_path, monkeypatch):
    # The temporary file's name carries the process id and the file name; the saved bytes must carry neither.
    payload = {"weights": torch.arange(6.0).reshape(2, 3), "name": "policy"}
    atomic_torch_save(payload, tmp_path / "first.pt")
    monkeypatch.setattr("carp.outputs.os.getpid", lambda: 123456)
    atomic_torch_save(payload, tmp_path / "first_copy.pt")
    assert (tmp_path / "first.pt").read_bytes() == (tmp_path / "first_copy.pt").read_bytes()
