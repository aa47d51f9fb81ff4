"""MLflow Model Registry for tokenizers and trained policies: register once per hash, resolve ``models:/name@alias``.

A tokenizer is logged as an MLflow pyfunc model whose artifact is the tokenizer directory, so
``mlflow.pyfunc.load_model(uri).unwrap_python_model().artifact.tokenizer`` is the real module (not a traced graph),
and ``predict`` turns raw action chunks into token sequences. A trained policy is logged the same way with its
checkpoint file (`policy.pt`) as the artifact; ``predict`` turns raw observation histories into action chunks. Both
go through one registration and one download: versions carry the sha256 (the tokenizer's weights, the policy's
checkpoint bytes) as a tag, registering the same hash again returns the existing version, and a download is checked
against the tag. Policies are named per task and family (:func:`policy_model_name`); the user moves an alias (e.g.
``champion``) to the version to serve, and `carp serve` follows it. The pipeline's ``register_policy`` stage
registers the checkpoint its evaluation confirmed on the test seeds (:func:`register_confirmed_policy`), tagged with
that evaluation, under one alias per training seed (:func:`policy_aliases`).
"""

import json
import logging
import shutil
import tempfile
import time
from collections.abc import Mapping, Sequence
from contextlib import nullcontext
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import mlflow
import numpy as np
import torch
from mlflow import MlflowClient
from mlflow.models import ModelSignature
from mlflow.types import ParamSchema, ParamSpec

from carp.config.checks import require_registry_alias
from carp.config.tokenizer_kinds import DEFAULT_TOKENIZER_KIND
from carp.data.sources import file_sha256
from carp.evaluation.selection import confirmed_checkpoint, find_candidates
from carp.outputs import write_text
from carp.tokenizer.artifact import TokenizerArtifact
from carp.tokenizer.kinds.artifact import KindArtifact, artifact_kind, load_any_artifact
from carp.tokenizer.kinds.base import KIND_FILENAME

logger = logging.getLogger(__name__)

SHA_TAG = "carp.sha256"
KIND_TAG = "carp.tokenizer_kind"
ACTION_SPACE_TAG = "carp.action_space"
ARTIFACT_KEY = "tokenizer"
POLICY_ARTIFACT_KEY = "policy"
POLICY_FILENAME = "policy.pt"
# Summary key of the evaluation (the evaluate stage's seed<k>.json) -> tag of the registered policy version.
EVALUATION_TAGS = {
    "training_seed": "carp.training_seed",
    "selected_epoch": "carp.selected_epoch",
    "selection": "carp.selection",
    "success_rate": "carp.test_success_rate",
    "episodes": "carp.test_episodes",
}
# Setting an alias is a read-then-insert on the server; writers that insert the same new alias at the same moment
# collide on its primary key, and a repeat (which then updates) settles it.
ALIAS_ATTEMPTS = 6


@dataclass(frozen=True)
class ModelReference:
    """One registered version, as an alias resolved to it (``models/tokenizer_ref.json`` holds the tokenizer's)."""

    name: str
    version: str
    alias: str
    run_id: str
    sha256: str

    @property
    def uri(self) -> str:
        """``models:/<name>@<alias>``."""
        return f"models:/{self.name}@{self.alias}"

    def save(self, path: Path) -> None:
        """Write as JSON (atomically)."""
        write_text(Path(path), json.dumps(asdict(self), indent=2))

    @classmethod
    def load(cls, path: Path) -> "ModelReference":
        """Read a reference file."""
        return cls(**json.loads(Path(path).read_text()))


TokenizerReference = ModelReference
"""The tokenizer's reference is a `ModelReference`; the name stays for the code that reads tokenizer references."""


class TokenizerModel(mlflow.pyfunc.PythonModel):
    """pyfunc wrapper: ``predict`` maps raw action chunks (B, H, A) of one task to token ids (B, L).

    Actions are normalized with the statistics of the task named by the ``task`` inference parameter, which may be
    omitted for a tokenizer trained on a single task (`carp.tokenizer.artifact`: normalization is per task). A
    variable-length kind (FAST) pads each row past its length with -1.
    """

    def load_context(self, context) -> None:
        """Load the tokenizer directory shipped with the model (any kind)."""
        self.artifact: TokenizerArtifact | KindArtifact = load_any_artifact(Path(context.artifacts[ARTIFACT_KEY]))

    def predict(self, context, model_input: np.ndarray, params: dict | None = None) -> np.ndarray:
        """Raw actions (B, H, A) or (B, H*A) -> token ids (B, L) int64; ``params["task"]`` picks the statistics."""
        tokenizer = self.artifact.tokenizer
        if isinstance(self.artifact, KindArtifact):
            horizon, action_dim = tokenizer.action_horizon, tokenizer.action_dim
        else:
            horizon, action_dim = tokenizer.spec.action_horizon, tokenizer.spec.action_dim
        actions = np.asarray(model_input, dtype=np.float32).reshape(-1, horizon, action_dim)
        task = (params or {}).get("task") or None
        normalized = torch.as_tensor(self.artifact.action_normalizer(task).normalize(actions)).float()
        with torch.inference_mode():
            if isinstance(self.artifact, KindArtifact):
                return tokenizer.encode(normalized).ids.numpy()
            return tokenizer.encode_to_sequence(normalized).numpy()


def registered_model_name(action_space: str, kind: str = DEFAULT_TOKENIZER_KIND) -> str:
    """``carp-tokenizer-<action-space>`` for ``carp_msvq``, ``carp-tokenizer-<kind>-<action-space>`` for the others.

    E.g. ``carp-tokenizer-panda-abs10`` and ``carp-tokenizer-fast-panda-abs10``.
    """
    if kind == DEFAULT_TOKENIZER_KIND:
        return f"carp-tokenizer-{action_space}"
    return f"carp-tokenizer-{kind}-{action_space}"


def register_tokenizer(
    tracking_uri: str, directory: Path, name: str, alias: str, run_id: str, sha256: str
) -> ModelReference:
    """Log and register the tokenizer in ``directory`` under ``name`` and point ``alias`` at it.

    Idempotent: if a version of ``name`` already carries ``sha256``, that version is reused (alias moved to it).
    The artifact is loaded first, so a tokenizer with a NaN or infinite weight, statistic or stored metric is never
    registered nor aliased.

    Args:
        tracking_uri: absolute MLflow tracking URI (the registry lives in the same store).
        directory: tokenizer artifact directory, of any kind (`carp.tokenizer.kinds.artifact.load_any_artifact`);
            the version is tagged with its kind and action space.
        name: registered model name.
        alias: alias to set on the version.
        run_id: the active MLflow run that logs the model.
        sha256: the weights' hash (tag of the version).

    Raises:
        carp.tokenizer.artifact.NonFiniteTokenizerError: the artifact holds a value that is not finite.
    """
    artifact = load_any_artifact(directory)
    return _register_version(
        tracking_uri,
        name,
        alias,
        sha256,
        artifact_path="tokenizer",
        python_model=TokenizerModel(),
        artifacts={ARTIFACT_KEY: str(directory)},
        # Declares the `task` inference parameter; MLflow drops parameters a signature does not name.
        signature=ModelSignature(inputs=None, params=ParamSchema([ParamSpec("task", "string", "")])),
        tags={KIND_TAG: artifact_kind(artifact), ACTION_SPACE_TAG: artifact.action_space},
    )


def _register_version(
    tracking_uri: str,
    name: str,
    alias: str,
    sha256: str,
    artifact_path: str,
    python_model,
    artifacts,
    signature=None,
    tags: Mapping[str, str] | None = None,
) -> ModelReference:
    """Register `python_model` with `artifacts` under `name` once per `sha256`, and point `alias` at that version.

    The model is logged in the active run unless a version of `name` already carries `sha256`, in which case the
    oldest such version is reused. `tags` are set on the version either way (before the alias moves to it), so a
    reused version carries the latest values.
    """
    client = MlflowClient(tracking_uri=tracking_uri)
    existing = [v for v in _versions(client, name) if v.tags.get(SHA_TAG) == sha256]
    if existing:
        version = min(existing, key=lambda v: int(v.version))
        logger.info("sha256 %s is already %s version %s", sha256[:12], name, version.version)
    else:
        mlflow.set_tracking_uri(tracking_uri)
        info = mlflow.pyfunc.log_model(
            name=artifact_path,
            python_model=python_model,
            artifacts=artifacts,
            pip_requirements=["torch", "numpy", "carp"],
            signature=signature,
        )
        mlflow.register_model(info.model_uri, name, tags={SHA_TAG: sha256})
        # Writers registering the same hash at once each add a version; all of them settle on the oldest.
        version = min(
            (v for v in _versions(client, name) if v.tags.get(SHA_TAG) == sha256), key=lambda v: int(v.version)
        )
    for key, value in (tags or {}).items():
        set_version_tag(client, name, str(version.version), key, value)
    aliased = point_alias(client, name, alias, str(version.version), sha256)
    return ModelReference(name=name, version=str(aliased.version), alias=alias, run_id=aliased.run_id, sha256=sha256)


def set_version_tag(client: MlflowClient, name: str, version: str, key: str, value: str) -> None:
    """Set tag ``key`` of version ``version`` of ``name`` to ``value``, safe beside writers setting it at once.

    A PostgreSQL store refuses one of two writers that insert the same new tag together (the tag's primary key); the
    tag is then read back and accepted when it already holds ``value``, otherwise the write is repeated.

    Raises:
        mlflow.exceptions.MlflowException: the tag could not be set in ``ALIAS_ATTEMPTS`` tries.
    """
    for attempt in range(ALIAS_ATTEMPTS - 1):
        try:
            client.set_model_version_tag(name, version, key, value)
            return
        except mlflow.exceptions.MlflowException:
            if client.get_model_version(name, version).tags.get(key) == value:
                return
            time.sleep(0.05 * 2**attempt)
    client.set_model_version_tag(name, version, key, value)


def point_alias(client: MlflowClient, name: str, alias: str, version: str, sha256: str):
    """Point ``alias`` of ``name`` at ``version`` (whose weights hash to ``sha256``); returns the aliased version.

    Safe beside other writers: when the server refuses the write because another writer set the same alias at the
    same moment, the alias is read back and accepted if it points at a version with the same weights; otherwise the
    write is repeated.

    Raises:
        mlflow.exceptions.MlflowException: the alias could not be set in ``ALIAS_ATTEMPTS`` tries.
    """
    for attempt in range(ALIAS_ATTEMPTS - 1):
        try:
            client.set_registered_model_alias(name, alias, version)
            return client.get_model_version(name, version)
        except mlflow.exceptions.MlflowException:
            try:
                current = client.get_model_version_by_alias(name, alias)
            except mlflow.exceptions.MlflowException:
                current = None
            if current is not None and current.tags.get(SHA_TAG) == sha256:
                return current
            time.sleep(0.05 * 2**attempt)
    client.set_registered_model_alias(name, alias, version)
    return client.get_model_version(name, version)


def _versions(client: MlflowClient, name: str) -> list:
    if not client.search_registered_models(filter_string=f"name = '{name}'"):
        return []
    return list(client.search_model_versions(filter_string=f"name = '{name}'"))


def parse_registry_uri(uri: str) -> tuple[str, str]:
    """``models:/<name>@<alias>`` -> (name, alias)."""
    body = uri.removeprefix("models:/")
    name, _, alias = body.partition("@")
    if not uri.startswith("models:/") or not name or not alias:
        raise ValueError(f"{uri!r} is not a registry URI of the form models:/<name>@<alias>")
    return name, alias


def resolve_alias(tracking_uri: str, uri: str) -> ModelReference:
    """The version ``models:/<name>@<alias>`` points at now (nothing is downloaded).

    Raises:
        ValueError: `uri` is not of that form.
        LookupError: no such registered model or alias.
    """
    name, alias = parse_registry_uri(uri)
    client = MlflowClient(tracking_uri=tracking_uri)
    try:
        version = client.get_model_version_by_alias(name, alias)
    except mlflow.exceptions.MlflowException as error:
        raise LookupError(f"{uri}: not found in the registry at {tracking_uri} ({error.message})") from None
    return ModelReference(name, str(version.version), alias, version.run_id, version.tags.get(SHA_TAG, ""))


def _download_version(tracking_uri: str, reference: ModelReference, destination: Path) -> Path:
    """Download the artifacts of `reference`'s version into `destination`; returns the local model directory."""
    mlflow.set_tracking_uri(tracking_uri)
    return Path(
        mlflow.artifacts.download_artifacts(
            artifact_uri=f"models:/{reference.name}/{reference.version}", dst_path=str(destination)
        )
    )


def fetch_registered_tokenizer(
    tracking_uri: str, uri: str, destination: Path | None = None
) -> tuple[TokenizerArtifact | KindArtifact, ModelReference]:
    """Resolve ``models:/<name>@<alias>``, download its tokenizer (any kind) and check its hash against the version tag.

    The download goes to ``destination`` when given (kept), else to a temporary directory that is removed on return.

    Raises:
        LookupError: no such registered model or alias.
        carp.tokenizer.artifact.TokenizerMismatchError: the downloaded weights do not hash to the version's sha256.
        carp.tokenizer.artifact.NonFiniteTokenizerError: the version holds a value that is not finite (registered
            before the registry refused such tokenizers).
    """
    try:
        reference = resolve_alias(tracking_uri, uri)
    except LookupError as error:
        raise LookupError(f"tokenizer {error}") from None
    with (
        tempfile.TemporaryDirectory(prefix="carp-tokenizer-") if destination is None else nullcontext(destination)
    ) as download_directory:
        local = _download_version(tracking_uri, reference, Path(download_directory))
        directories = [p.parent for p in local.rglob(KIND_FILENAME)] or [p.parent for p in local.rglob("tokenizer.pt")]
        if not directories:
            raise LookupError(f"tokenizer {uri}: version {reference.version} has no tokenizer artifact")
        artifact = load_any_artifact(directories[0], reference.sha256 or None, f"the registered version {uri}")
    return artifact, replace(reference, sha256=artifact.sha256)


def policy_model_name(task: str, family: str) -> str:
    """``carp-policy-<task>-<family>``, e.g. ``carp-policy-lift-carp``: one registered model per task and family."""
    return f"carp-policy-{task}-{family}"


class PolicyModel(mlflow.pyfunc.PythonModel):
    """pyfunc wrapper: ``predict`` maps raw observation histories (B, To, Do) to raw action chunks (B, H, A).

    Greedy or the family's default inference settings, one draw per call; `carp serve` is the way to run a policy
    for a robot (per-episode draws and histories), this face is for inspecting a registered version.
    """

    def load_context(self, context) -> None:
        """Load the checkpoint shipped with the model."""
        from carp.policies.registry import load_policy

        self.policy = load_policy(Path(context.artifacts[POLICY_ARTIFACT_KEY]))

    def predict(self, context, model_input: np.ndarray, params: dict | None = None) -> np.ndarray:
        """Raw observations (B, To, Do) float32 -> raw actions (B, H, A) float32."""
        return self.policy.predict_action(np.asarray(model_input, dtype=np.float32))


def register_policy(
    tracking_uri: str,
    checkpoint: Path,
    name: str,
    alias: str,
    sha256: str,
    tags: Mapping[str, str] | None = None,
) -> ModelReference:
    """Log and register the policy checkpoint at `checkpoint` (in the active run) under `name`; point `alias` at it.

    Idempotent like :func:`register_tokenizer`: a version already carrying `sha256` is reused.

    Args:
        tracking_uri: absolute MLflow tracking URI.
        checkpoint: a policy checkpoint file (`policy.pt`, a snapshot, an averaged policy); the version stores it as
            `policy.pt`.
        name: registered model name (:func:`policy_model_name`).
        alias: alias to point at the version.
        sha256: hex sha256 of the checkpoint's bytes (tag of the version).
        tags: further tags set on the version.
    """
    checkpoint = Path(checkpoint)
    with tempfile.TemporaryDirectory(prefix="carp-policy-") as staging:
        if checkpoint.name != POLICY_FILENAME:
            # The artifact keeps the file's name, and a download (`fetch_registered_policy`) looks for policy.pt.
            staged = Path(staging) / POLICY_FILENAME
            shutil.copyfile(checkpoint, staged)
            checkpoint = staged
        return _register_version(
            tracking_uri,
            name,
            alias,
            sha256,
            artifact_path="policy",
            python_model=PolicyModel(),
            artifacts={POLICY_ARTIFACT_KEY: str(checkpoint)},
            tags=tags,
        )


def fetch_registered_policy(tracking_uri: str, reference: ModelReference, destination: Path) -> Path:
    """Download the checkpoint of the resolved `reference` (:func:`resolve_alias`) into `destination`.

    Returns:
        The local `policy.pt`, whose bytes hash to the version's sha256 tag.

    Raises:
        LookupError: the version holds no `policy.pt`, or one whose bytes do not hash to its tag.
    """
    local = _download_version(tracking_uri, reference, Path(destination))
    found = sorted(local.rglob(POLICY_FILENAME))
    if not found:
        raise LookupError(f"{reference.uri}: version {reference.version} has no {POLICY_FILENAME} artifact")
    digest = file_sha256(found[0])
    if reference.sha256 and digest != reference.sha256:
        raise LookupError(
            f"{reference.uri}: version {reference.version}'s {POLICY_FILENAME} has sha256 {digest[:12]}..., not the "
            f"{reference.sha256[:12]}... its tag records"
        )
    return found[0]


def register_policy_checkpoint(tracking_uri: str, checkpoint: Path, alias: str) -> ModelReference:
    """Register the trained policy at `checkpoint` as :func:`policy_model_name` of its task and family.

    Opens its own tracking run (experiment ``carp-<task>``, run ``register_policy@<task>-<family>``) that logs the
    checkpoint as the version's artifact, unless the same bytes are registered already.

    Raises:
        ValueError: the checkpoint does not name its task, or `alias` is one the registry refuses or reserves
            (`carp.config.require_registry_alias`; a `ConfigError`).
        carp.training.checkpoint.CheckpointError: the file is not a readable policy checkpoint.
    """
    from carp.tracking.runs import stage_run

    require_registry_alias("alias", alias)
    task, family, source_run = _trained_policy(checkpoint)
    tags = {"carp.policy_type": family, "carp.source_run": source_run}
    with stage_run(tracking_uri, f"carp-{task}", f"register_policy@{task}-{family}", {}, tags):
        name = policy_model_name(task, family)
        return register_policy(tracking_uri, checkpoint, name, alias, file_sha256(checkpoint))


def _trained_policy(checkpoint: Path) -> tuple[str, str, str]:
    """The task, family and training run id the checkpoint at `checkpoint` records (it is loaded, so it is sound).

    Raises:
        ValueError: the checkpoint does not name its task.
        carp.training.checkpoint.CheckpointError: the file is not a readable policy checkpoint.
    """
    from carp.policies.registry import load_policy

    policy = load_policy(checkpoint)
    task = policy.metadata.get("task")
    if not task:
        raise ValueError(f"{checkpoint}: the checkpoint does not name the task it was trained on")
    return task, policy.policy_type, str(policy.metadata.get("mlflow_run_id"))


def policy_aliases(alias: str, seed: int, seeds: Sequence[int]) -> tuple[str, ...]:
    """The aliases the pipeline points at training seed `seed`'s version, the seed's own first.

    ``<alias>-seed<seed>`` always, and ``<alias>`` itself when `seed` is the first of `seeds`, so that
    ``models:/<name>@<alias>`` names one policy the pipeline trained however many seeds it trains.
    """
    per_seed = f"{alias}-seed{seed}"
    return (per_seed, alias) if seed == seeds[0] else (per_seed,)


def evaluation_tags(evaluation: Mapping[str, Any]) -> dict[str, str]:
    """The version tags (:data:`EVALUATION_TAGS`) of an evaluation summary.

    Training seed, selected epoch, selection rule, and the success rate and episodes on the test seeds.

    Raises:
        ValueError: the summary lacks one of them (written before the summary recorded it).
    """
    missing = [key for key in EVALUATION_TAGS if key not in evaluation]
    if missing:
        raise ValueError(f"the evaluation summary lacks {missing} (evaluate the policy again)")
    return {tag: str(evaluation[key]) for key, tag in EVALUATION_TAGS.items()}


def register_confirmed_policy(
    tracking_uri: str,
    policy_dir: Path,
    epoch_losses: Sequence[float],
    evaluation_path: Path,
    aliases: Sequence[str],
) -> ModelReference:
    """Register (in the active run) the checkpoint that an evaluation ran on the test seeds, and point `aliases` at it.

    The checkpoint is the candidate the evaluation summary names (`carp.evaluation.selection.confirmed_checkpoint`:
    a snapshot, the final policy, or the average rebuilt as the evaluation built it), registered as
    :func:`policy_model_name` of the task and family it records, with :func:`evaluation_tags`. The same bytes keep
    their version.

    Args:
        tracking_uri: absolute MLflow tracking URI.
        policy_dir: the training run's directory (`policy.pt`, `snapshots/`).
        epoch_losses: the run's mean training loss per epoch (its history), which numbers the final policy's epoch.
        evaluation_path: the evaluation summary of that run (the evaluate stage's JSON).
        aliases: at least one; the returned reference names the first.

    Raises:
        FileNotFoundError: the run has no final policy, or there is no summary.
        ValueError: a summary that is not JSON, lacks a tag's value or does not fit the run (the message names it),
            an alias the registry refuses or reserves (a `ConfigError`), or a checkpoint that does not name its task.
        carp.training.checkpoint.CheckpointError: a checkpoint is not a readable policy checkpoint.
    """
    if not aliases:
        raise ValueError("there is no alias to point at the registered policy")
    for alias in aliases:
        require_registry_alias("alias", alias)
    candidates = find_candidates(policy_dir, epoch_losses)
    with tempfile.TemporaryDirectory(prefix="carp-register-") as scratch:
        try:
            evaluation = json.loads(Path(evaluation_path).read_text())
            tags = evaluation_tags(evaluation)
            checkpoint = confirmed_checkpoint(candidates, evaluation, Path(scratch))
        except ValueError as error:
            raise ValueError(f"{evaluation_path}: {error}") from None
        task, family, _ = _trained_policy(checkpoint)
        name, sha256 = policy_model_name(task, family), file_sha256(checkpoint)
        reference = register_policy(tracking_uri, checkpoint, name, aliases[0], sha256, tags)
    client = MlflowClient(tracking_uri=tracking_uri)
    for alias in aliases[1:]:
        point_alias(client, name, alias, reference.version, sha256)
    return reference
