"""From a checkpoint file to a running server: what `carp serve` calls.

The spec comes from the checkpoint itself: training records the serving protocol (`carp.serving.protocol`: the
observation keys and widths, `To`, `H`, `Ta`, the cameras) in its metadata, `Do` and `A` come from the policy's
normalizers, which every PyTorch family keeps (`carp.policies.wrapper.PolicyModule`), and the control period from the
checkpoint's task. The inference settings are not recorded (they are evaluation params, changing them must not
retrain): they come from the params when given (`inference.<family>` for the checkpoint's task, as evaluation takes
them), otherwise from the family's defaults.

A checkpoint trained before the protocol was recorded is served only with the params it was trained with: the spec
then comes from their `data` section, as evaluation takes it (`carp.evaluation.runner`), and requests must send the
concatenated ``obs`` (the per-key widths are unknown). The warm-up checks the predicted (H, A) against the spec.
"""

from pathlib import Path

from carp.policies.base import Policy
from carp.serving.model import ModelSource, ServedModel, file_sha256
from carp.serving.protocol import recorded_protocol, spec_from_protocol
from carp.serving.server import PolicyServer, ServerSettings, serve_forever
from carp.serving.session import ServingSpec


class ServingStartError(RuntimeError):
    """The server cannot start; the message is one line that names the file or setting at fault."""


def _policy_dims(policy: Policy) -> tuple[int, int]:
    try:
        return policy.obs_normalizer.num_features, policy.action_normalizer.num_features
    except AttributeError:
        raise ServingStartError(
            f"a {policy.policy_type} policy does not expose obs_normalizer and action_normalizer, so Do and A "
            "are unknown"
        ) from None


def serving_spec(policy: Policy, params, task: str) -> ServingSpec:
    """The spec of `policy`, trained on `task` with `params` (a `carp.config.Params`), without a recorded protocol.

    For a checkpoint trained before checkpoints recorded it; the key widths stay unknown.

    Raises:
        ServingStartError: the policy does not expose its normalizers.
    """
    from carp.tasks import get_task

    data = params.data
    obs_dim, action_dim = _policy_dims(policy)
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
        cameras=data.cameras if image_shape is not None else (),
    )


def recorded_spec(policy: Policy, task: str) -> ServingSpec | None:
    """The spec the checkpoint of `policy`, trained on `task`, records; None when it records none.

    Raises:
        ServingStartError: the policy does not expose its normalizers.
        ProtocolError: the recorded protocol is of another format or does not fit the policy.
    """
    from carp.tasks import get_task

    protocol = recorded_protocol(policy.metadata)
    if protocol is None:
        return None
    obs_dim, action_dim = _policy_dims(policy)
    return spec_from_protocol(protocol, obs_dim, action_dim, 1.0 / get_task(task).control_frequency_hz)


def default_inference(family: str, task: str) -> dict:
    """The inference settings of `family` on `task` when no params are given: its `inference.<family>` defaults."""
    from carp.policies.registry import get_sections

    return get_sections(family)[1]().settings_for(task)


def load_served_model(model_path: Path, params=None) -> tuple[ServedModel, ServingSpec]:
    """Load the checkpoint at `model_path`, apply its inference settings and derive its spec.

    Args:
        model_path: a policy checkpoint (`policy.pt`).
        params: a `carp.config.Params` whose `inference.<family>` settings apply (and whose `data` section gives
            the spec of a checkpoint that does not record it); None for the family's default settings.

    Raises:
        ServingStartError: no such file, an unreadable checkpoint, one without the task it was trained on, or one
            without a recorded protocol and no params.
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
        spec = recorded_spec(policy, task)
        if spec is None and params is None:
            raise ServingStartError(
                f"{model_path}: the checkpoint does not record its serving protocol (trained before carp recorded "
                "it); train it again, or pass --params with the params it was trained with"
            )
        if spec is None:
            spec = serving_spec(policy, params, task)
        if params is not None:
            inference = params.inference_settings(policy.policy_type, task)
        else:
            inference = default_inference(policy.policy_type, task)
        policy.configure_inference(**inference)
    except (KeyError, TypeError, ValueError) as error:
        raise ServingStartError(f"{model_path}: {error}") from None
    source = ModelSource(path=str(model_path), sha256=file_sha256(model_path))
    return ServedModel(policy, source, inference), spec


def serve_checkpoint(model_path: Path, params, settings: ServerSettings) -> None:
    """Serve the checkpoint at `model_path` with `settings` until interrupted; `params` as `load_served_model`.

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
