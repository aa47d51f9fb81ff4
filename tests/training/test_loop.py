"""The shared loop's family hooks: one-time data preparation, per-batch metric sums, the optimizer it builds."""

import pytest
import torch
from torch import nn

from carp.config import TrainingConfig
from carp.training.loop import (
    SNAPSHOT_DIRNAME,
    OptimizerRecipe,
    PolicyTrainingData,
    TrainingStep,
    make_optimizer,
    matrix_decay_groups,
    snapshot_path,
    train_with_loss,
)
from carp.training.run import TrainingRun

COUNT = 10


class LinearPolicy(nn.Module):
    """The least a loop needs: a policy type and a loss."""

    policy_type = "linear"

    def __init__(self) -> None:
        super().__init__()
        self.linear = nn.Linear(6, 8)

    def training_loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        return nn.functional.mse_loss(self.linear(batch["obs"].flatten(1)), batch["actions"].flatten(1))


def _data() -> PolicyTrainingData:
    generator = torch.Generator().manual_seed(0)
    return PolicyTrainingData(
        torch.rand(COUNT, 2, 3, generator=generator), torch.rand(COUNT, 4, 2, generator=generator)
    )


def _train(tmp_path, prepare_data=None, training_step=None, on_epoch_end=None, epochs: int = 3) -> LinearPolicy:
    torch.manual_seed(0)
    training = TrainingConfig(epochs=epochs, batch_size=4, checkpoint_every=1)
    recipe = OptimizerRecipe(learning_rate=1e-2)
    run = TrainingRun(training, context=None, data=_data(), checkpoint_dir=tmp_path, on_epoch_end=on_epoch_end)
    return train_with_loss(
        LinearPolicy(), run, recipe, {"name": "linear"}, prepare_data=prepare_data, training_step=training_step
    )


def test_prepared_extras_reach_every_batch_and_metric_sums_become_epoch_means(tmp_path):
    prepared, seen, history = [], [], []

    def prepare(data: PolicyTrainingData) -> PolicyTrainingData:
        prepared.append(data)
        return PolicyTrainingData(data.obs, data.actions, extras={"window": torch.arange(COUNT)})

    policy = LinearPolicy()

    def step(batch: dict[str, torch.Tensor]) -> TrainingStep:
        seen.append(batch["window"])
        # Per-window metric: the window's index / 10, so the epoch mean is 0.45 whatever the (ragged) batches.
        return TrainingStep(policy.training_loss(batch), {"index_fraction": (batch["window"].double() / COUNT).sum()})

    _train(tmp_path, prepare, step, lambda epoch, metrics: history.append(metrics))
    assert len(prepared) == 1 and prepared[0].obs.dtype == torch.float32
    # 3 epochs of batches 4, 4, 2: every window once per epoch, in a new order each epoch.
    assert [batch.numel() for batch in seen] == [4, 4, 2] * 3
    epochs = [torch.cat(seen[index : index + 3]) for index in (0, 3, 6)]
    assert all(sorted(order.tolist()) == list(range(COUNT)) for order in epochs)
    assert not torch.equal(epochs[0], epochs[1])
    assert [metrics["index_fraction"] for metrics in history] == pytest.approx([0.45] * 3, abs=1e-15)
    assert list(history[0]) == ["loss", "index_fraction", "learning_rate", "epoch_seconds", "samples_per_second"]


def test_without_hooks_the_policy_loss_trains_and_resuming_repeats_the_metrics(tmp_path):
    history, replayed = [], []
    trained = _train(tmp_path, on_epoch_end=lambda epoch, metrics: history.append(metrics))
    assert list(history[0]) == ["loss", "learning_rate", "epoch_seconds", "samples_per_second"]
    assert history[-1]["loss"] < history[0]["loss"]
    finished = _train(tmp_path, on_epoch_end=lambda epoch, metrics: replayed.append(metrics))
    assert replayed == history
    assert torch.equal(finished.linear.weight, trained.linear.weight)


def test_adamw_is_fused_on_the_cpu():
    recipe = OptimizerRecipe(learning_rate=1e-3, betas=(0.9, 0.95))
    optimizer = make_optimizer(list(LinearPolicy().parameters()), recipe, torch.device("cpu"))
    assert optimizer.defaults["fused"] is True
    assert optimizer.defaults["betas"] == (0.9, 0.95)


def test_matrix_decay_groups_decay_weight_matrices_only():
    module = nn.ModuleDict(
        {
            "linear": nn.Linear(3, 4),
            "norm": nn.LayerNorm(4),
            "token_embedding": nn.Embedding(5, 4),
            "frozen": nn.Linear(2, 2).requires_grad_(False),
        }
    )
    decayed, undecayed = matrix_decay_groups(module, 0.1)
    assert decayed["weight_decay"] == 0.1 and undecayed["weight_decay"] == 0.0
    assert decayed["params"] == [module["linear"].weight]
    names = {id(parameter): name for name, parameter in module.named_parameters()}
    assert sorted(names[id(parameter)] for parameter in undecayed["params"]) == [
        "linear.bias",
        "norm.bias",
        "norm.weight",
        "token_embedding.weight",
    ]


class SavingPolicy(LinearPolicy):
    """A linear policy that saves its weights, as a family's policy saves its checkpoint."""

    def save(self, path) -> None:
        torch.save({name: value.clone() for name, value in self.state_dict().items()}, path)


def _train_with_snapshots(tmp_path, epochs: int, ema: bool = False) -> SavingPolicy:
    from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

    torch.manual_seed(0)
    training = TrainingConfig(epochs=epochs, batch_size=4, checkpoint_every=1, snapshot_every=2, snapshot_last=1)
    average = (lambda module: AveragedModel(module, multi_avg_fn=get_ema_multi_avg_fn(0.5))) if ema else None
    recipe = OptimizerRecipe(learning_rate=1e-2, ema=average)
    run = TrainingRun(training, context=None, data=_data(), checkpoint_dir=tmp_path)
    return train_with_loss(SavingPolicy(), run, recipe, {"name": "saving"})


def test_snapshots_are_kept_at_the_asked_epochs_and_hold_the_averaged_weights(tmp_path):
    final = _train_with_snapshots(tmp_path, epochs=5, ema=True)
    snapshots = sorted(path.name for path in (tmp_path / SNAPSHOT_DIRNAME).iterdir())
    assert snapshots == ["epoch0002.pt", "epoch0004.pt", "epoch0005.pt"]
    # The last epoch's snapshot is what evaluation loads: the EMA weights the returned policy holds.
    last = torch.load(snapshot_path(tmp_path / SNAPSHOT_DIRNAME, 5))
    assert torch.equal(last["linear.weight"], final.linear.weight)
    assert not torch.equal(
        torch.load(snapshot_path(tmp_path / SNAPSHOT_DIRNAME, 2))["linear.weight"], last["linear.weight"]
    )


def test_a_fresh_run_clears_snapshots_a_resumed_run_keeps_them(tmp_path):
    snapshot_dir = tmp_path / SNAPSHOT_DIRNAME
    snapshot_dir.mkdir()
    stale = snapshot_path(snapshot_dir, 3)
    stale.write_bytes(b"from another run")
    _train_with_snapshots(tmp_path, epochs=2)
    assert sorted(path.name for path in snapshot_dir.iterdir()) == ["epoch0002.pt"]
    kept = snapshot_path(snapshot_dir, 2).read_bytes()
    # The finished state resumes at its last epoch: nothing retrains, the snapshot stays as it was.
    _train_with_snapshots(tmp_path, epochs=2)
    assert snapshot_path(snapshot_dir, 2).read_bytes() == kept


def test_snapshot_epochs_combine_every_n_and_the_last_k():
    assert TrainingConfig(snapshot_every=3, snapshot_last=2).snapshot_epochs(10) == (3, 6, 9, 10)
    assert TrainingConfig(snapshot_last=20).snapshot_epochs(3) == (1, 2, 3)
    assert TrainingConfig().snapshot_epochs(10) == ()
