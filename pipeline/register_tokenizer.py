"""register_tokenizer stage: models/tokenizer/ -> MLflow Model Registry version + models/tokenizer_ref.json.

With ``tokenizer.source: pipeline`` the tokenizer trained here is registered (idempotently: identical weights keep
their version) as ``carp-tokenizer-<action-space>`` with ``tokenizer.registry_alias``. With a registry URI
(``models:/<name>@<alias>``) nothing is registered: the reference file points at that version instead.
"""

from stage_support import (
    TOKENIZER_DIR,
    TOKENIZER_REF,
    fail,
    load,
    mlflow_stage,
    parse_args,
    setup_logging,
    tracking_uri,
)

from carp.tokenizer.artifact import (
    NonFiniteTokenizerError,
    TokenizerMismatchError,
    check_compatible,
    load_tokenizer_artifact,
)
from carp.tracking.registry import fetch_registered_tokenizer, register_tokenizer, registered_model_name
from carp.training.checkpoint import CheckpointError


def main() -> None:
    setup_logging()
    params = load(parse_args(__doc__).params)
    uri = tracking_uri(params)
    try:
        if params.tokenizer.source == "pipeline":
            artifact = load_tokenizer_artifact(TOKENIZER_DIR)
            check_compatible(artifact, params.action_space, params.scales, params.codebook_size)
            name = registered_model_name(params.action_space)
            with mlflow_stage(params, "register_tokenizer", "tokenizer") as run:
                reference = register_tokenizer(
                    uri, TOKENIZER_DIR, name, params.tokenizer.registry_alias, run.run_id, artifact.sha256
                )
        else:
            artifact, reference = fetch_registered_tokenizer(uri, params.tokenizer.source)
            check_compatible(artifact, params.action_space, params.scales, params.codebook_size)
    except (LookupError, TokenizerMismatchError, NonFiniteTokenizerError, CheckpointError, FileNotFoundError) as error:
        fail(str(error))
    TOKENIZER_REF.parent.mkdir(parents=True, exist_ok=True)
    reference.save(TOKENIZER_REF)
    print(f"tokenizer {reference.uri} = version {reference.version} (sha256 {reference.sha256[:12]})")


if __name__ == "__main__":
    main()
