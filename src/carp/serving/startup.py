"""From a checkpoint file or a registered version to a running server: what `carp serve` calls.

`--model` is a `policy.pt` path or a registry URI ``models:/<name>@<alias>`` (`carp.tracking.registry`: one
registered model per task and family, an alias the user moves). The served version, its sha256 and the alias it came
from are in the metadata; :func:`model_reloader` tells the server when the alias has moved (or the file changed).

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

import logging
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from carp.policies.base import TORCH_BACKEND, Policy
from carp.serving.access import is_loopback, tls_context
from carp.serving.model import ModelSource, ServedModel, file_sha256
from carp.serving.protocol import PROTOCOL_FORMAT, ProtocolError, recorded_protocol
from carp.serving.server import PolicyServer, ServerSettings, serve_forever
from carp.serving.session import ServingSpec

REGISTRY_PREFIX = "models:/"
logger = logging.getLogger(__name__)


class ServingStartError(RuntimeError):
    """The server cannot start; the message is one line that names the file or setting at fault."""


def spec_from_protocol(
    protocol: Mapping[str, Any], obs_dim: int, action_dim: int, control_period_s: float
) -> ServingSpec:
    """The serving spec a recorded protocol describes.

    Args:
        protocol: the map :func:`training_protocol` made.
        obs_dim: `Do` of the policy (its observation normalizer's width); must equal the sum of the key widths.
        action_dim: `A` of the policy.
        control_period_s: seconds between two control steps of the policy's task.

    Raises:
        ProtocolError: another format, a missing entry, or key widths that do not add up to `obs_dim`.
    """
    if protocol.get("format") != PROTOCOL_FORMAT:
        raise ProtocolError(f"serving protocol format {protocol.get('format')!r}, this carp reads {PROTOCOL_FORMAT}")
    try:
        keys, widths = tuple(protocol["obs_keys"]), tuple(protocol["obs_widths"])
        image_shape = None
        if protocol["observations"] == "image":
            size = protocol["image_size"]
            image_shape = (len(protocol["cameras"]), 3, size, size)
        spec = ServingSpec(
            obs_keys=keys,
            obs_steps=protocol["obs_steps"],
            obs_dim=obs_dim,
            action_horizon=protocol["action_horizon"],
            action_dim=action_dim,
            action_steps=protocol["action_steps"],
            control_period_s=control_period_s,
            image_shape=image_shape,
            obs_widths=widths,
            cameras=tuple(protocol["cameras"]),
        )
    except KeyError as error:
        raise ProtocolError(f"the serving protocol lacks {error}") from None
    except ValueError as error:
        raise ProtocolError(f"the serving protocol does not fit the policy: {error}") from None
    return spec


def _selected_padding(policy: Policy):
    """The selected task's observation padding of a multi-task policy (`carp.data.obs_padding`), else None."""
    tasks = getattr(policy, "tasks", None)
    return None if tasks is None else tasks.padding()


def _policy_dims(policy: Policy) -> tuple[int, int]:
    """`Do` of the observations the policy takes (a padded multi-task policy: its selected task's own) and `A`."""
    padding = _selected_padding(policy)
    try:
        obs_dim = policy.obs_normalizer.num_features if padding is None else padding.input_dim
        return obs_dim, policy.action_normalizer.num_features
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
    padding = _selected_padding(policy)
    if padding is not None:
        # One protocol serves every task of a multi-task policy; the served task's key widths are its own.
        protocol = {**protocol, "obs_widths": list(padding.widths)}
    obs_dim, action_dim = _policy_dims(policy)
    frequency = protocol.get("control_frequency_hz") or get_task(task).control_frequency_hz
    return spec_from_protocol(protocol, obs_dim, action_dim, 1.0 / frequency)


def default_inference(family: str, task: str) -> dict:
    """The inference settings of `family` on `task` when no params are given: its `inference.<family>` defaults."""
    from carp.policies.registry import get_sections

    return get_sections(family)[1]().settings_for(task)


def is_registry_uri(model: str | Path) -> bool:
    """Whether `model` names a registered version (``models:/<name>@<alias>``) rather than a file."""
    return isinstance(model, str) and model.startswith(REGISTRY_PREFIX)


def load_served_model(
    model: str | Path,
    params=None,
    tracking_uri: str | None = None,
    backend: str = TORCH_BACKEND,
    task: str | None = None,
) -> tuple[ServedModel, ServingSpec]:
    """Load the policy `model` names, apply its inference settings and derive its spec.

    Args:
        model: a policy checkpoint (`policy.pt`), or a registry URI ``models:/<name>@<alias>`` whose version is
            downloaded (and checked against its sha256 tag) into a temporary directory, loaded, and removed.
        params: a `carp.config.Params` whose `inference.<family>` settings apply (and whose `data` section gives
            the spec of a checkpoint that does not record it); None for the family's default settings.
        tracking_uri: the MLflow store holding the registry; needed for a registry URI only.
        backend: what runs the predictions, as evaluation's `eval.backend`: `torch`, or `onnxruntime` for a family
            that exports graphs (CARP on state observations; others stay in PyTorch). The metadata names the one
            that runs.
        task: the task served: required for a multi-task policy (one of its tasks, whose statistics and task id it
            then uses); for a single-task policy None or the task it was trained on.

    Raises:
        ServingStartError: no such file, model or alias, an unreadable checkpoint, one without the task it was
            trained on, a task the policy was not trained on (or none for a multi-task policy), or a checkpoint
            without a recorded protocol and no params.
    """
    if not is_registry_uri(model):
        return _load_checkpoint(Path(model), params, backend=backend, task=task)
    return _load_registered(str(model), _resolve(str(model), tracking_uri), params, tracking_uri, backend, task)


def _resolve(uri: str, tracking_uri: str | None):
    from carp.tracking.registry import resolve_alias

    if tracking_uri is None:
        raise ServingStartError(f"{uri}: a registry URI needs the tracking URI of the registry (--tracking-uri)")
    try:
        return resolve_alias(tracking_uri, uri)
    except (LookupError, ValueError) as error:
        raise ServingStartError(str(error)) from None


def _load_registered(
    uri: str, reference, params, tracking_uri: str, backend: str, task: str | None = None
) -> tuple[ServedModel, ServingSpec]:
    from carp.tracking.registry import fetch_registered_policy

    with tempfile.TemporaryDirectory(prefix="carp-serve-") as folder:
        try:
            checkpoint = fetch_registered_policy(tracking_uri, reference, Path(folder))
        except LookupError as error:
            raise ServingStartError(str(error)) from None
        source = ModelSource(uri, file_sha256(checkpoint), reference.name, reference.version, reference.alias)
        return _load_checkpoint(checkpoint, params, source, backend, task)


def _load_checkpoint(
    model_path: Path,
    params,
    source: ModelSource | None = None,
    backend: str = TORCH_BACKEND,
    task: str | None = None,
) -> tuple[ServedModel, ServingSpec]:
    """Load the checkpoint file at `model_path`; `source` names it (default: the path and its sha256)."""
    from carp.policies.registry import load_policy
    from carp.training.checkpoint import CheckpointError

    label = model_path if source is None else source.path
    if not model_path.is_file():
        raise ServingStartError(f"{label}: no such model file")
    try:
        policy = load_policy(model_path)
    except (CheckpointError, OSError) as error:
        raise ServingStartError(str(error) if source is None else f"{label}: {error}") from None
    task = _served_task(policy, task, label)
    try:
        spec = recorded_spec(policy, task)
        if spec is None and params is None:
            raise ServingStartError(
                f"{label}: the checkpoint does not record its serving protocol (trained before carp recorded "
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
        raise ServingStartError(f"{label}: {error}") from None
    policy, backend = _deployed(policy, model_path, backend)
    if source is None:
        source = ModelSource(path=str(model_path), sha256=file_sha256(model_path))
    return ServedModel(policy, source, inference, backend=backend, task=task), spec


def _served_task(policy: Policy, requested: str | None, label) -> str:
    """The task `policy` serves: `requested`, selected in a multi-task policy, or the single task it was trained on."""
    if policy.tasks is not None:
        if requested is None:
            raise ServingStartError(
                f"{label}: a multi-task policy over {list(policy.tasks.names)}; name the task to serve (--task)"
            )
        try:
            policy.select_task(requested)
        except ValueError as error:
            raise ServingStartError(f"{label}: {error}") from None
        return requested
    trained = policy.metadata.get("task")
    if not trained:
        raise ServingStartError(f"{label}: the checkpoint does not name the task it was trained on")
    if requested is not None and requested != trained:
        raise ServingStartError(f"{label}: task {requested!r}: this policy was trained on {trained!r} only")
    return trained


def _deployed(policy: Policy, model_path: Path, backend: str) -> tuple[Policy, str]:
    """`policy` as `backend` runs it (`Policy.deployment`, as in evaluation), and the backend that does run it."""
    if backend == TORCH_BACKEND:
        return policy, TORCH_BACKEND
    with tempfile.TemporaryDirectory(prefix="carp-serve-graphs-") as folder:
        if policy.tasks is not None:
            # A deployment that loads the file again must find the served task selected in it, as evaluation does.
            model_path = Path(folder) / "selected_task.pt"
            policy.save(model_path)
        deployment = policy.deployment(model_path, backend, Path(folder))
        if deployment.backend == TORCH_BACKEND:
            return policy, TORCH_BACKEND
        # The runtime reads the exported graphs while it loads them, so their folder need not outlive this.
        return deployment.load(), deployment.backend


def model_reloader(
    model: str | Path,
    params=None,
    tracking_uri: str | None = None,
    backend: str = TORCH_BACKEND,
    task: str | None = None,
) -> Callable[[ModelSource], tuple[ServedModel, ServingSpec] | None]:
    """What `PolicyServer` calls to find out whether to serve another model, for `model` as `load_served_model`.

    For a registry URI the alias is resolved again: a version other than the served one is loaded. For a file, its
    bytes are hashed again: other bytes are loaded. Otherwise it returns None (nothing is downloaded or loaded).
    """

    def reload(served: ModelSource) -> tuple[ServedModel, ServingSpec] | None:
        if is_registry_uri(model):
            reference = _resolve(str(model), tracking_uri)
            if reference.version == served.version:
                return None
            return _load_registered(str(model), reference, params, tracking_uri, backend, task)
        path = Path(model)
        if path.is_file() and file_sha256(path) == served.sha256:
            return None
        return _load_checkpoint(path, params, backend=backend, task=task)

    return reload


def serve_checkpoint(
    model: str | Path,
    params,
    settings: ServerSettings,
    tracking_uri: str | None = None,
    backend: str = TORCH_BACKEND,
    task: str | None = None,
) -> None:
    """Serve `model` (as `load_served_model` loads it) with `settings` until interrupted, following it.

    Raises:
        ServingStartError: the model cannot be loaded, the address cannot be bound, or the warm-up prediction does
            not fit the spec.
    """
    if settings.tls_certificate is not None:
        try:
            tls_context(settings.tls_certificate, settings.tls_key)  # refused before the model takes seconds to load
        except ValueError as error:
            raise ServingStartError(str(error)) from None
    elif not is_loopback(settings.host):
        if settings.token is None:
            logger.warning("serving %s without a token: anyone who reaches the port drives the policy", settings.host)
        else:
            logger.warning("serving %s without TLS: the token crosses the network in clear text", settings.host)
    served, spec = load_served_model(model, params, tracking_uri, backend, task)
    reloader = model_reloader(model, params, tracking_uri, backend, task)
    try:
        serve_forever(PolicyServer(served, spec, settings, reloader))
    except OSError as error:
        address = f"{settings.host}:{settings.port}"
        raise ServingStartError(f"cannot listen on {address}: {error.strerror or error}") from None
    except ValueError as error:
        raise ServingStartError(str(error)) from None
