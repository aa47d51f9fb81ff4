"""The `carp` console command: `carp serve` serves a trained policy to robots, `carp register` registers one.

`carp export-lerobot data/raw/lift.hdf5 --out exports/lift` writes a task's demos as a LeRobotDataset v3.0 folder
(`carp.data.lerobot.export`).

`carp serve --model` takes a checkpoint path or a registry URI ``models:/<name>@<alias>``; the checkpoint describes
what it serves (`carp.serving.protocol`), `--params` only chooses the inference settings (and gives the spec of a
checkpoint trained before checkpoints recorded it). `carp register --model policy.pt --alias champion` registers a
checkpoint as ``carp-policy-<task>-<family>`` and points the alias at it; moving the alias later makes a running
`carp serve` swap versions. Like a pipeline stage script, this module only parses arguments, loads the params and
calls one library function; it lives in the package because a console script must be importable.
Errors print one `error: ...` line and exit with status 1.
"""

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from carp.config.serving import ServingConfig

TOKEN_VARIABLE = "CARP_SERVE_TOKEN"
TRACKING_VARIABLE = "MLFLOW_TRACKING_URI"
DEFAULT_TRACKING_URI = "sqlite:///mlflow.db"
DEFAULT_RELOAD_INTERVAL_S = 30.0


def _parser() -> argparse.ArgumentParser:
    from carp.serving.settings import DEFAULT_HOST, DEFAULT_MAX_REQUEST_BYTES, DEFAULT_PORT

    parser = argparse.ArgumentParser(prog="carp", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    serve = commands.add_parser("serve", help="serve a policy checkpoint over WebSocket (msgpack frames)")
    serve.add_argument(
        "--model", required=True, help="policy checkpoint (models/policy/.../policy.pt) or models:/<name>@<alias>"
    )
    serve.add_argument(
        "--params",
        type=Path,
        default=None,
        help="params whose inference.<family> settings apply (default: the family's defaults); for a checkpoint that "
        "does not record its serving protocol, the params it was trained with",
    )
    serve.add_argument(
        "--host",
        default=DEFAULT_HOST,
        help="interface to bind (default: loopback only; any other needs a token or --allow-no-token)",
    )
    serve.add_argument("--port", type=int, default=DEFAULT_PORT)
    serve.add_argument(
        "--token-file",
        type=Path,
        default=None,
        help=f"file whose first line is the token clients must send (default: ${TOKEN_VARIABLE}, else none)",
    )
    serve.add_argument(
        "--token",
        default=None,
        help="the token itself; visible to every local user in the process list, so prefer --token-file or "
        f"${TOKEN_VARIABLE}",
    )
    serve.add_argument(
        "--allow-no-token",
        action="store_true",
        help="serve a non-loopback --host without a token (anyone who reaches the port may drive the policy)",
    )
    serve.add_argument("--tls-cert", default=None, help="PEM certificate (chain) to serve TLS with (wss://, https://)")
    serve.add_argument("--tls-key", default=None, help="PEM private key of --tls-cert (default: in the same file)")
    serve.add_argument("--max-request-bytes", type=int, default=DEFAULT_MAX_REQUEST_BYTES)
    serve.add_argument(
        "--max-batch",
        type=int,
        default=None,
        help="most requests of a greedy PyTorch policy in one prediction call (default: serving.max_batch of --params, "
        "else 1: off; a batched chunk may differ from the one predicted alone where a token choice is a near tie)",
    )
    serve.add_argument(
        "--batch-window-ms",
        type=float,
        default=None,
        help="milliseconds a request waits for others to share its PyTorch call (default: serving.batch_window_ms "
        "of --params, else 0: none; 0 to 1000)",
    )
    serve.add_argument(
        "--prediction-threads",
        type=int,
        default=None,
        help="ONNX Runtime calls run at once, one request each (default: serving.prediction_threads of --params, "
        "else 0: one per CPU core)",
    )
    serve.add_argument(
        "--backend",
        choices=("onnxruntime", "torch"),
        default="onnxruntime",
        help="what runs the predictions: ONNX Runtime graphs for CARP on state observations, as evaluation runs them "
        "(one request per call, --prediction-threads calls at once; other families stay in PyTorch), or PyTorch "
        "(one call at a time, batching the requests of several clients; default: onnxruntime)",
    )
    serve.add_argument(
        "--task",
        default=None,
        help="task to serve: required for a multi-task policy (models/policy/multitask/...), one of its tasks",
    )
    serve.add_argument(
        "--reload-interval",
        type=float,
        default=DEFAULT_RELOAD_INTERVAL_S,
        help="seconds between checks for a moved alias or a changed file (0: only on SIGHUP)",
    )
    register = commands.add_parser("register", help="register a policy checkpoint in the MLflow Model Registry")
    register.add_argument("--model", type=Path, required=True, help="policy checkpoint (policy.pt)")
    register.add_argument("--alias", default="candidate", help="alias to point at the version (default: candidate)")
    export = commands.add_parser("export-lerobot", help="write a robomimic-schema demo file as a LeRobotDataset")
    export.add_argument("source", type=Path, help="robomimic-schema HDF5 of a registered task (data/raw/<task>.hdf5)")
    export.add_argument("--out", type=Path, required=True, help="the LeRobotDataset folder to write (replaced)")
    for command in (serve, register):
        command.add_argument(
            "--tracking-uri",
            default=os.environ.get(TRACKING_VARIABLE, DEFAULT_TRACKING_URI),
            help=f"MLflow store of the registry (or ${TRACKING_VARIABLE}; default {DEFAULT_TRACKING_URI}, relative "
            "to the working directory)",
        )
    return parser


def _token(args: argparse.Namespace) -> str | None:
    """The token of `--token`, else of `--token-file`, else of the environment; None for none.

    Raises:
        OSError: the token file cannot be read.
        ValueError: the token file is empty.
    """
    if args.token is not None:
        logging.getLogger("carp.cli").warning(
            "--token is visible to every local user in the process list; pass it in $%s or --token-file instead",
            TOKEN_VARIABLE,
        )
        return args.token
    if args.token_file is not None:
        try:
            lines = args.token_file.read_text().splitlines()
        except FileNotFoundError:
            raise FileNotFoundError(f"{args.token_file}: no such token file") from None
        if not lines or not lines[0].strip():
            raise ValueError(f"{args.token_file}: the token file's first line is empty")
        return lines[0].strip()
    return os.environ.get(TOKEN_VARIABLE) or None


def main(argv: list[str] | None = None) -> None:
    """Parse `argv` (default: the process's) and run the command."""
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s", stream=sys.stderr)
    if args.command == "export-lerobot":
        _export_lerobot(args.source, args.out)
        return
    from carp.config.checks import ConfigError
    from carp.config.loading import load_params
    from carp.serving.startup import ServingStartError
    from carp.tracking.runs import resolve_tracking_uri

    tracking_uri = resolve_tracking_uri(args.tracking_uri, Path.cwd())
    try:
        if args.command == "register":
            from carp.tracking.registry import register_policy_checkpoint

            if not args.model.is_file():
                raise FileNotFoundError(f"{args.model}: no such model file")
            reference = register_policy_checkpoint(tracking_uri, args.model, args.alias)
            print(f"{reference.uri} = version {reference.version} (sha256 {reference.sha256[:12]})")
            return
        from carp.serving.settings import ServerSettings
        from carp.serving.startup import serve_checkpoint

        interval = args.reload_interval if args.reload_interval > 0 else None
        params = load_params(args.params) if args.params is not None else None
        prediction = _prediction_settings(args, None if params is None else params.serving)
        settings = ServerSettings(
            args.host,
            args.port,
            _token(args),
            args.max_request_bytes,
            prediction.max_batch,
            reload_interval_s=interval,
            batch_window_s=prediction.batch_window_ms / 1e3,
            prediction_threads=prediction.prediction_threads,
            tls_certificate=args.tls_cert,
            tls_key=args.tls_key,
            allow_no_token=args.allow_no_token,
        )
        serve_checkpoint(args.model, params, settings, tracking_uri, args.backend, args.task)
    except (ServingStartError, ConfigError, OSError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(1)


def _prediction_settings(args: argparse.Namespace, section: "ServingConfig | None") -> "ServingConfig":
    """The prediction settings, checked as the params section is (a `ConfigError` names the key).

    Each flag given on the command line wins, else the params' `serving` section, else its defaults.
    """
    from carp.config.serving import ServingConfig

    base = section if section is not None else ServingConfig()
    flags = {
        "max_batch": args.max_batch,
        "batch_window_ms": args.batch_window_ms,
        "prediction_threads": args.prediction_threads,
    }
    return ServingConfig(**{name: getattr(base, name) if value is None else value for name, value in flags.items()})


def _export_lerobot(source: Path, output: Path) -> None:
    from carp.data.lerobot.export import export_lerobot
    from carp.data.robomimic_schema import DatasetError

    try:
        summary = export_lerobot(source, output)
    except (DatasetError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(1)
    cameras = f", cameras {list(summary.cameras)}" if summary.cameras else ""
    print(f"{output}: {summary.episodes} episodes, {summary.frames} frames at {summary.fps} fps{cameras}")


if __name__ == "__main__":
    main()
