"""From a checkpoint file and the project's params to a running server: what `carp serve` calls.

The spec comes from where evaluation takes it (`carp.evaluation.runner`): `To`, `H`, `Ta`, the observation keys and
the cameras from the params' `data` section, the inference settings from `inference.<family>` for the checkpoint's
task, the control period from the task. `Do` and `A` come from the policy's normalizers, which every PyTorch family
keeps (`carp.policies.wrapper.PolicyModule`); the warm-up then checks the predicted (H, A) against the spec.
"""

from pathlib import Path

from carp.policies.base import Policy
from carp.serving.model import ModelSource, ServedModel, file_sha256
from carp.serving.server import PolicyServer, ServerSettings, serve_forever
from carp.serving.session import ServingSpec


class ServingStartError(RuntimeError):
    """The server cannot start; the message is one line that names the file or setting at fault."""


def serving_spec(policy: Policy, params, task: str) -> ServingSpec:
    """The spec of `policy`, trained on `task` with `params` (a `carp.config.Params`).

    Raises:
        ServingStartError: the policy does not expose its normalizers.
    """
    from carp.tasks import get_task

    data = params.data
    try:
        obs_dim, action_dim = policy.obs_normalizer.num_features, policy.action_normalizer.num_features
    except AttributeError:
        raise ServingStartError(
            f"a {policy.policy_type} policy does not expose obs_normalizer and action_normalizer, so Do and A "
            "are unknown"
        ) from None
    image_shape = None
    if data.observations == "image":
        image_shape = (len(data.cameras), 3, data.image_size, data.image_size)
    return ServingSpec(
        obs_keys=params.obs_keys_for(task),
        obs_steps=data.obs_steps,
        obs_dim=obs_dim,
        action_horizon=data.action_horizon,
        action_dim=action_dim,
        action_steps=data.action_steps,
        control_period_s=1.0 / get_task(task).control_frequency_hz,
        image_shape=image_shape,
    )


def load_served_model(model_path: Path, params) -> tuple[ServedModel, ServingSpec]:
    """Load the checkpoint at `model_path`, apply its inference settings and derive its spec.

    Raises:
        ServingStartError: no such file, an unreadable checkpoint, or one without the task it was trained on.
    """
    from carp.policies.registry import load_policy
    from carp.training.checkpoint import CheckpointError

    model_path = Path(model_path)
    if not model_path.is_file():
        raise ServingStartError(f"{model_path}: no such model file")
    try:
        policy = load_policy(model_path)
    except (CheckpointError, OSError) as error:
        raise ServingStartError(str(error)) from None
    task = policy.metadata.get("task")
    if not task:
        raise ServingStartError(f"{model_path}: the checkpoint does not name the task it was trained on")
    try:
        inference = params.inference_settings(policy.policy_type, task)
        policy.configure_inference(**inference)
        spec = serving_spec(policy, params, task)
    except (KeyError, TypeError, ValueError) as error:
        raise ServingStartError(f"{model_path}: {error}") from None
    source = ModelSource(path=str(model_path), sha256=file_sha256(model_path))
    return ServedModel(policy, source, inference), spec


def serve_checkpoint(model_path: Path, params, settings: ServerSettings) -> None:
    """Serve the checkpoint at `model_path` with `settings` until interrupted.

    Raises:
        ServingStartError: the model cannot be loaded, the address cannot be bound, or the warm-up prediction does
            not fit the spec.
    """
    model, spec = load_served_model(model_path, params)
    try:
        serve_forever(PolicyServer(model, spec, settings))
    except OSError as error:
        address = f"{settings.host}:{settings.port}"
        raise ServingStartError(f"cannot listen on {address}: {error.strerror or error}") from None
    except ValueError as error:
        raise ServingStartError(str(error)) from None
