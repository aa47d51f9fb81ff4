"""register_tokenizer stage: models/tokenizer/ -> MLflow Model Registry version + models/tokenizer_ref.json.

With ``tokenizer.source: pipeline`` the tokenizer trained here is registered (idempotently: identical weights keep
their version) as ``carp-tokenizer-<action-space>`` (``carp-tokenizer-<kind>-<action-space>`` for a kind other than
carp_msvq), tagged with its kind and action space, with ``tokenizer.registry_alias``. With a registry URI
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

from carp.tokenizer.artifact import NonFiniteTokenizerError, TokenizerMismatchError
from carp.tokenizer.kinds.artifact import check_fits_params, load_any_artifact
from carp.tracking.registry import fetch_registered_tokenizer, register_tokenizer, registered_model_name
from carp.training.checkpoint import CheckpointError


def main() -> None:
    setup_logging()
    params = load(parse_args(__doc__).params)
    uri, config = tracking_uri(params), params.tokenizer
    fits = (config.kind, params.action_space, params.data.action_horizon, params.scales, params.codebook_size)
    try:
        if config.source == "pipeline":
            artifact = load_any_artifact(TOKENIZER_DIR)
            check_fits_params(artifact, *fits)
            name = registered_model_name(params.action_space, config.kind)
            with mlflow_stage(params, "register_tokenizer", "tokenizer") as run:
                alias, sha256 = config.registry_alias, artifact.sha256
                reference = register_tokenizer(uri, TOKENIZER_DIR, name, alias, run.run_id, sha256)
        else:
            artifact, reference = fetch_registered_tokenizer(uri, config.source)
            try:
                check_fits_params(artifact, *fits)
            except TokenizerMismatchError as error:
                fail(f"{config.source}: {error}")
    except (LookupError, TokenizerMismatchError, NonFiniteTokenizerError, CheckpointError, FileNotFoundError) as error:
        fail(str(error))
    TOKENIZER_REF.parent.mkdir(parents=True, exist_ok=True)
    reference.save(TOKENIZER_REF)
    print(f"tokenizer {reference.uri} = version {reference.version} (sha256 {reference.sha256[:12]})")


if __name__ == "__main__":
    main()
