"""MLflow Model Registry for tokenizers: register once per weights hash, resolve ``models:/<name>@<alias>``.

A tokenizer is logged as an MLflow pyfunc model whose artifact is the tokenizer directory, so
``mlflow.pyfunc.load_model(uri).unwrap_python_model().artifact.tokenizer`` is the real module (not a traced graph),
and ``predict`` turns raw action chunks into token sequences. Versions carry the weights' sha256 as a tag; registering
identical weights again returns the existing version.
"""

import json
import logging
import os
import tempfile
import time
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path

import mlflow
import numpy as np
import torch
from mlflow import MlflowClient
from mlflow.models import ModelSignature
from mlflow.types import ParamSchema, ParamSpec

from carp.tokenizer.artifact import TokenizerArtifact, load_tokenizer_artifact

logger = logging.getLogger(__name__)

SHA_TAG = "carp.sha256"
ARTIFACT_KEY = "tokenizer"
# Setting an alias is a read-then-insert on the server; writers that insert the same new alias at the same moment
# collide on its primary key, and a repeat (which then updates) settles it.
ALIAS_ATTEMPTS = 6


@dataclass(frozen=True)
class TokenizerReference:
    """What ``models/tokenizer_ref.json`` holds."""

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
        temporary = Path(path).with_name(f".{Path(path).name}.tmp")
        temporary.write_text(json.dumps(asdict(self), indent=2))
        os.replace(temporary, path)

    @classmethod
    def load(cls, path: Path) -> "TokenizerReference":
        """Read a reference file."""
        return cls(**json.loads(Path(path).read_text()))


class TokenizerModel(mlflow.pyfunc.PythonModel):
    """pyfunc wrapper: ``predict`` maps raw action chunks (B, H, A) of one task to token sequences (B, L).

    Actions are normalized with the statistics of the task named by the ``task`` inference parameter, which may be
    omitted for a tokenizer trained on a single task (`carp.tokenizer.artifact`: normalization is per task).
    """

    def load_context(self, context) -> None:
        """Load the tokenizer directory shipped with the model."""
        self.artifact: TokenizerArtifact = load_tokenizer_artifact(Path(context.artifacts[ARTIFACT_KEY]))

    def predict(self, context, model_input: np.ndarray, params: dict | None = None) -> np.ndarray:
        """Raw actions (B, H, A) or (B, H*A) -> token ids (B, L) int64; ``params["task"]`` picks the statistics."""
        spec = self.artifact.tokenizer.spec
        actions = np.asarray(model_input, dtype=np.float32).reshape(-1, spec.action_horizon, spec.action_dim)
        task = (params or {}).get("task") or None
        normalized = torch.as_tensor(self.artifact.action_normalizer(task).normalize(actions))
        with torch.inference_mode():
            return self.artifact.tokenizer.encode_to_sequence(normalized).numpy()


def registered_model_name(action_space: str) -> str:
    """``carp-tokenizer-<action-space>``, e.g. ``carp-tokenizer-panda-abs10``."""
    return f"carp-tokenizer-{action_space}"


def register_tokenizer(
    tracking_uri: str, directory: Path, name: str, alias: str, run_id: str, sha256: str
) -> TokenizerReference:
    """Log and register the tokenizer in ``directory`` under ``name`` and point ``alias`` at it.

    Idempotent: if a version of ``name`` already carries ``sha256``, that version is reused (alias moved to it).
    The artifact is loaded first, so a tokenizer with a NaN or infinite weight, statistic or stored metric is never
    registered nor aliased.

    Args:
        tracking_uri: absolute MLflow tracking URI (the registry lives in the same store).
        directory: tokenizer artifact directory.
        name: registered model name.
        alias: alias to set on the version.
        run_id: the active MLflow run that logs the model.
        sha256: the weights' hash (tag of the version).

    Raises:
        carp.tokenizer.artifact.NonFiniteTokenizerError: the artifact holds a value that is not finite.
    """
    load_tokenizer_artifact(directory)
    client = MlflowClient(tracking_uri=tracking_uri)
    existing = [v for v in _versions(client, name) if v.tags.get(SHA_TAG) == sha256]
    if existing:
        version = min(existing, key=lambda v: int(v.version))
        logger.info("tokenizer with sha256 %s is already %s version %s", sha256[:12], name, version.version)
    else:
        mlflow.set_tracking_uri(tracking_uri)
        info = mlflow.pyfunc.log_model(
            name="tokenizer",
            python_model=TokenizerModel(),
            artifacts={ARTIFACT_KEY: str(directory)},
            pip_requirements=["torch", "numpy", "carp"],
            # Declares the `task` inference parameter; MLflow drops parameters a signature does not name.
            signature=ModelSignature(inputs=None, params=ParamSchema([ParamSpec("task", "string", "")])),
        )
        mlflow.register_model(info.model_uri, name, tags={SHA_TAG: sha256})
        # Writers registering the same weights at once each add a version; all of them settle on the oldest.
        version = min(
            (v for v in _versions(client, name) if v.tags.get(SHA_TAG) == sha256), key=lambda v: int(v.version)
        )
    aliased = point_alias(client, name, alias, str(version.version), sha256)
    return TokenizerReference(
        name=name, version=str(aliased.version), alias=alias, run_id=aliased.run_id, sha256=sha256
    )


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
        raise ValueError(f"tokenizer source {uri!r} is not of the form models:/<name>@<alias>")
    return name, alias


def fetch_registered_tokenizer(
    tracking_uri: str, uri: str, destination: Path | None = None
) -> tuple[TokenizerArtifact, TokenizerReference]:
    """Resolve ``models:/<name>@<alias>``, download its tokenizer and check the weights' hash against the version tag.

    The download goes to ``destination`` when given (kept), else to a temporary directory that is removed on return.

    Raises:
        LookupError: no such registered model or alias.
        carp.tokenizer.artifact.TokenizerMismatchError: the downloaded weights do not hash to the version's sha256.
        carp.tokenizer.artifact.NonFiniteTokenizerError: the version holds a value that is not finite (registered
            before the registry refused such tokenizers).
    """
    name, alias = parse_registry_uri(uri)
    client = MlflowClient(tracking_uri=tracking_uri)
    try:
        version = client.get_model_version_by_alias(name, alias)
    except mlflow.exceptions.MlflowException as error:
        raise LookupError(f"tokenizer {uri}: not found in the registry at {tracking_uri} ({error.message})") from None
    mlflow.set_tracking_uri(tracking_uri)
    with (
        tempfile.TemporaryDirectory(prefix="carp-tokenizer-") if destination is None else nullcontext(destination)
    ) as download_directory:
        local = mlflow.artifacts.download_artifacts(
            artifact_uri=f"models:/{name}/{version.version}", dst_path=str(download_directory)
        )
        directories = [p.parent for p in Path(local).rglob("tokenizer.pt")]
        if not directories:
            raise LookupError(f"tokenizer {uri}: version {version.version} has no tokenizer.pt artifact")
        artifact = load_tokenizer_artifact(directories[0], expected_sha256=version.tags.get(SHA_TAG))
    reference = TokenizerReference(name, str(version.version), alias, version.run_id, artifact.sha256)
    return artifact, reference
