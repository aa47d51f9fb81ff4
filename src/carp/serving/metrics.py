"""The server's counters and latency histogram, rendered in the Prometheus text exposition format (version 0.0.4).

Written by hand rather than through `prometheus_client`: a few series do not justify a dependency. All updates happen
on the server's event loop thread, so no lock is needed.
"""

import bisect
from dataclasses import dataclass, field

LATENCY_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5)
"""Upper bounds (seconds) of the latency histogram: a chunk takes milliseconds on a GPU, up to a second on a CPU."""

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


@dataclass
class ServerMetrics:
    """Counts since the server started.

    Attributes:
        requests: request frames received (answered with actions or with an error).
        errors: request frames answered with an error.
        connections: WebSocket connections currently open.
        bucket_counts: per `LATENCY_BUCKETS_S` bound, answered requests that took longer than the previous bound and
            at most this one (not cumulative; rendering accumulates).
        slower: answered requests slower than the last bound.
        latency_sum_s: total seconds of the answered requests, from frame received to reply sent.
        model_calls: prediction calls; below `predicted_chunks` when requests were batched.
        predicted_chunks: chunks predicted (one per request that asked for one and got it).
        reloads: models swapped in after the first one.
    """

    requests: int = 0
    errors: int = 0
    connections: int = 0
    bucket_counts: list[int] = field(default_factory=lambda: [0] * len(LATENCY_BUCKETS_S))
    slower: int = 0
    latency_sum_s: float = 0.0
    model_calls: int = 0
    predicted_chunks: int = 0
    reloads: int = 0

    def observe_latency(self, seconds: float) -> None:
        """Add one answered request's latency to the histogram."""
        index = bisect.bisect_left(LATENCY_BUCKETS_S, seconds)
        if index == len(LATENCY_BUCKETS_S):
            self.slower += 1
        else:
            self.bucket_counts[index] += 1
        self.latency_sum_s += seconds

    def render(self) -> str:
        """The metrics in the Prometheus text format."""
        lines = [
            "# HELP carp_serving_requests_total Request frames received.",
            "# TYPE carp_serving_requests_total counter",
            f"carp_serving_requests_total {self.requests}",
            "# HELP carp_serving_errors_total Request frames answered with an error.",
            "# TYPE carp_serving_errors_total counter",
            f"carp_serving_errors_total {self.errors}",
            "# HELP carp_serving_connections WebSocket connections open.",
            "# TYPE carp_serving_connections gauge",
            f"carp_serving_connections {self.connections}",
            "# HELP carp_serving_model_calls_total Prediction calls (one call answers a whole batch).",
            "# TYPE carp_serving_model_calls_total counter",
            f"carp_serving_model_calls_total {self.model_calls}",
            "# HELP carp_serving_predicted_chunks_total Action chunks predicted.",
            "# TYPE carp_serving_predicted_chunks_total counter",
            f"carp_serving_predicted_chunks_total {self.predicted_chunks}",
            "# HELP carp_serving_reloads_total Models swapped in after the first.",
            "# TYPE carp_serving_reloads_total counter",
            f"carp_serving_reloads_total {self.reloads}",
            "# HELP carp_serving_request_seconds Seconds from a request frame received to its reply sent.",
            "# TYPE carp_serving_request_seconds histogram",
        ]
        cumulative = 0
        for bound, count in zip(LATENCY_BUCKETS_S, self.bucket_counts):
            cumulative += count
            lines.append(f'carp_serving_request_seconds_bucket{{le="{bound}"}} {cumulative}')
        cumulative += self.slower
        lines += [
            f'carp_serving_request_seconds_bucket{{le="+Inf"}} {cumulative}',
            f"carp_serving_request_seconds_sum {self.latency_sum_s!r}",
            f"carp_serving_request_seconds_count {cumulative}",
        ]
        return "\n".join(lines) + "\n"
