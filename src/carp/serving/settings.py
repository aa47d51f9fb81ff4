"""Where and how the policy server listens, and the protocol constants its clients read (`carp.serving.server`)."""

from dataclasses import dataclass

from carp.serving.access import is_loopback

PROTOCOL_NAME = "carp-policy"
PROTOCOL_VERSION = 1
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8000
DEFAULT_MAX_REQUEST_BYTES = 1 << 20
"""1 MiB: two 84 x 84 cameras take 42 kB a step; a larger image policy raises it."""
DEFAULT_MAX_BATCH_SIZE = 1
"""Batching is opt-in: a batched row may differ from the chunk predicted alone (a greedy token flips on a near tie,
docs/serving.md measures how often), so by default every request is predicted as the in-process evaluation would."""
DEFAULT_DECODING_THREADS = 2
DEFAULT_REFUSAL_PAUSE_S = 0.05
"""After refusing a request, the seconds before the server reads that connection's next frame: a correct client
rarely pays it, and a client that sends nothing but refused frames (a hostile one) gets at most 20 of them a second
decoded, so that their decoding cannot crowd out the other connections' frames."""
SPEC_CHANGED_CLOSE_CODE = 1012
SPEC_CHANGED_REASON = "the policy's observation or action spec changed: reconnect and read the metadata again"


@dataclass(frozen=True)
class ServerSettings:
    """Where and how the server listens.

    Attributes:
        host: interface to bind; loopback unless the robot is on another machine. Another address needs a token
            unless `allow_no_token` says otherwise.
        port: TCP port; 0 picks a free one (tests).
        token: bearer token required on every route but `/healthz`; None serves without one.
        max_request_bytes: largest request frame answered; larger ones get an error reply.
        max_batch_size: most requests predicted in one call (`carp.serving.batching`); 1 (the default) turns
            batching off, so that every chunk equals the in-process prediction bit for bit.
        reload_interval_s: seconds between two checks for a new model (the registry alias moved, the file changed);
            None checks only when asked (SIGHUP).
        batch_window_s: seconds the first waiting request of a batching policy waits for others to join its call;
            0 predicts at once (only the requests that arrived during the previous call share it).
        prediction_threads: ONNX Runtime calls that run at once (one request each); 0 for one per CPU core. A
            PyTorch policy predicts one call at a time whatever this says.
        decoding_threads: threads that decode and validate request frames off the event loop.
        tls_certificate: PEM certificate chain to serve TLS with (``wss://``); None serves plain TCP.
        tls_key: PEM private key of `tls_certificate`; None when the certificate file holds it.
        allow_no_token: serve a non-loopback `host` without a token (anyone who reaches the port may drive the
            robot's policy); refused otherwise.
        refusal_pause_s: seconds a connection waits, after a request of its was refused, before its next frame is
            read; 0 reads it at once.
    """

    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    token: str | None = None
    max_request_bytes: int = DEFAULT_MAX_REQUEST_BYTES
    max_batch_size: int = DEFAULT_MAX_BATCH_SIZE
    reload_interval_s: float | None = None
    batch_window_s: float = 0.0
    prediction_threads: int = 0
    decoding_threads: int = DEFAULT_DECODING_THREADS
    tls_certificate: str | None = None
    tls_key: str | None = None
    allow_no_token: bool = False
    refusal_pause_s: float = DEFAULT_REFUSAL_PAUSE_S

    def __post_init__(self) -> None:
        if self.token is not None and not self.token:
            raise ValueError("the token must not be empty (leave it unset to serve without one)")
        if self.token is not None and (self.token != self.token.strip() or any(c in self.token for c in "\r\n")):
            raise ValueError("the token must not hold whitespace at its ends or line breaks")
        if self.token is None and not self.allow_no_token and not is_loopback(self.host):
            raise ValueError(
                f"host {self.host!r} is reachable from other machines: set a token ($CARP_SERVE_TOKEN or "
                "--token-file), or allow serving without one explicitly (--allow-no-token)"
            )
        if not 0 <= self.batch_window_s <= 1:
            raise ValueError(f"batch_window_s must be between 0 and 1 second, got {self.batch_window_s}")
        if self.prediction_threads < 0:
            raise ValueError(f"prediction_threads must be >= 0 (0: one per CPU core), got {self.prediction_threads}")
        if not 0 <= self.refusal_pause_s <= 10:
            raise ValueError(f"refusal_pause_s must be between 0 and 10 seconds, got {self.refusal_pause_s}")
        if self.decoding_threads < 1:
            raise ValueError(f"decoding_threads must be >= 1, got {self.decoding_threads}")
        if self.tls_key is not None and self.tls_certificate is None:
            raise ValueError("a TLS key needs its certificate (tls_certificate)")
        if self.max_request_bytes < 1:
            raise ValueError(f"max_request_bytes must be positive, got {self.max_request_bytes}")
        if self.max_batch_size < 1:
            raise ValueError(f"max_batch_size must be >= 1, got {self.max_batch_size}")
        if self.reload_interval_s is not None and not self.reload_interval_s > 0:
            raise ValueError(f"reload_interval_s must be positive, got {self.reload_interval_s}")
