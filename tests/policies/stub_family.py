"""A whole policy family in one small file: a linear regressor from observations to the action chunk.

It proves the seam: registered with `register_family`, it trains, saves, loads and evaluates through carp's own code
with no change anywhere else.
"""

import functools
import time
from dataclasses import asdict, dataclass

import torch
from torch import nn

from carp.data.normalizer import MinMaxNormalizer
from carp.policies.base import POLICY_FORMAT_VERSION, Deployment, TimedPrediction, count_parameters
from carp.policies.registry import PolicyFamily, load_policy
from carp.training.checkpoint import atomic_torch_save
from carp.training.loop import OptimizerRecipe
from carp.training.runtime import seed_everything


@dataclass(frozen=True)
class StubConfig:
    """The params section `stub`: nothing to choose but a bias switch."""

    use_bias: bool = True


@dataclass(frozen=True)
class StubInference:
    """The section `inference.stub`: no settings."""

    def settings_for(self, task: str) -> dict:
        return {}


class StubPolicy(nn.Module):
    policy_type, description, model_calls_per_chunk = "stub", "linear", 1

    def __init__(self, config, obs_norm, action_norm, obs_steps, horizon, metadata) -> None:
        super().__init__()
        self.config, self.obs_norm, self.action_norm, self.metadata = config, obs_norm, action_norm, dict(metadata)
        self.shape = (obs_steps, obs_norm.num_features, horizon, action_norm.num_features)
        self.linear = nn.Linear(obs_steps * self.shape[1], horizon * self.shape[3], bias=config.use_bias)

    num_parameters = property(count_parameters)
    tasks = None

    def select_task(self, task) -> None:
        pass

    def forward(self, obs):  # (B, To, Do) normalized -> (B, H, A) normalized
        return self.linear(obs.flatten(1)).view(-1, self.shape[2], self.shape[3])

    def training_loss(self, batch):
        return nn.functional.mse_loss(self(batch["obs"]), batch["actions"])

    def configure_inference(self) -> None:
        pass

    def predict_action_timed(self, obs, task_index=None, generator=None) -> TimedPrediction:
        with torch.inference_mode():
            started = time.perf_counter()
            normalized = self(self.obs_norm.normalize(torch.as_tensor(obs, dtype=torch.float32)))
            predicted = time.perf_counter()
            actions = self.action_norm.unnormalize(normalized).float().numpy()
        return TimedPrediction(actions, predicted - started, time.perf_counter() - predicted, 1)

    def predict_action(self, obs, task_index=None, generator=None):
        return self.predict_action_timed(obs, task_index, generator).actions

    def deployment(self, checkpoint_path, backend, directory) -> Deployment:
        return Deployment("torch", functools.partial(load_policy, checkpoint_path))

    def to_checkpoint(self) -> dict:
        norms = {"obs": self.obs_norm.to_dict(), "action": self.action_norm.to_dict()}
        return {"format_version": POLICY_FORMAT_VERSION, "policy_type": "stub", "config": asdict(self.config),
                "shape": self.shape, "norms": norms, "state": self.state_dict(), "metadata": self.metadata}  # fmt: skip

    def save(self, path) -> None:
        atomic_torch_save(self.to_checkpoint(), path)


def from_checkpoint(checkpoint: dict) -> StubPolicy:
    obs_steps, _, horizon, _ = checkpoint["shape"]
    norms = {key: MinMaxNormalizer.from_dict(value) for key, value in checkpoint["norms"].items()}
    policy = StubPolicy(StubConfig(**checkpoint["config"]), norms["obs"], norms["action"], obs_steps, horizon,
                        checkpoint["metadata"])  # fmt: skip
    policy.load_state_dict(checkpoint["state"], strict=True)
    return policy


def build(config: StubConfig, context) -> StubPolicy:
    return StubPolicy(config, context.obs_normalizer, context.action_normalizer, context.obs_steps,
                      context.action_horizon, context.metadata)  # fmt: skip


def train(config, run):
    seed_everything(run.training.seed)
    return run.train_with_loss(build(config, run.context), OptimizerRecipe(learning_rate=1e-2), asdict(config))


STUB_FAMILY = PolicyFamily("stub", StubConfig, StubInference, build, from_checkpoint, train)
