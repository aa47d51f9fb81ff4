"""The `carp` console command: `carp serve --model <policy.pt>` serves a trained policy to robots (issue 69).

The checkpoint describes what it serves (`carp.serving.protocol`); `--params` only chooses the inference settings
(and gives the spec of a checkpoint trained before checkpoints recorded it). Like a pipeline stage script, this module
only parses arguments, loads the params and calls one library function (`carp.serving.startup.serve_checkpoint`); it
lives in the package because a console script must be importable.
Start-up errors print one `error: ...` line and exit with status 1.
"""

import argparse
import logging
import os
import sys
from pathlib import Path

TOKEN_VARIABLE = "CARP_SERVE_TOKEN"


def _parser() -> argparse.ArgumentParser:
    from carp.serving.server import DEFAULT_HOST, DEFAULT_MAX_REQUEST_BYTES, DEFAULT_PORT

    parser = argparse.ArgumentParser(prog="carp", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    serve = commands.add_parser("serve", help="serve a policy checkpoint over WebSocket (msgpack frames)")
    serve.add_argument("--model", type=Path, required=True, help="policy checkpoint (models/policy/.../policy.pt)")
    serve.add_argument(
        "--params",
        type=Path,
        default=None,
        help="params whose inference.<family> settings apply (default: the family's defaults); for a checkpoint that "
        "does not record its serving protocol, the params it was trained with",
    )
    serve.add_argument("--host", default=DEFAULT_HOST, help="interface to bind (default: loopback only)")
    serve.add_argument("--port", type=int, default=DEFAULT_PORT)
    serve.add_argument(
        "--token", default=os.environ.get(TOKEN_VARIABLE), help=f"bearer token clients must send (or ${TOKEN_VARIABLE})"
    )
    serve.add_argument("--max-request-bytes", type=int, default=DEFAULT_MAX_REQUEST_BYTES)
    return parser


def main(argv: list[str] | None = None) -> None:
    """Parse `argv` (default: the process's) and run the command."""
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s", stream=sys.stderr)
    from carp.config import ConfigError, load_params
    from carp.serving.server import ServerSettings
    from carp.serving.startup import ServingStartError, serve_checkpoint

    try:
        settings = ServerSettings(args.host, args.port, args.token, args.max_request_bytes)
        params = load_params(args.params) if args.params is not None else None
        serve_checkpoint(args.model, params, settings)
    except (ServingStartError, ConfigError, OSError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
