"""The `serving` section: how `carp serve --params` predicts for several robots (`carp.serving.batching`)."""

from dataclasses import dataclass

from carp.config.checks import _require


@dataclass(frozen=True)
class ServingConfig:
    """Prediction settings of `carp serve`, read with ``--params``; the flags of the same meaning override them.

    Attributes:
        max_batch: Most requests of a greedy PyTorch policy predicted in one call; an integer >= 1. 1 predicts each
            request alone, so that every chunk equals the in-process prediction bit for bit; above 1 a batched chunk
            may differ where a greedy token choice is a near tie (docs/serving.md measures how often).
        batch_window_ms: Milliseconds the first waiting request of a batching policy waits for others to share its
            call; 0 predicts at once (only requests that arrived during the previous call share the next); a number
            in [0, 1000].
        prediction_threads: ONNX Runtime calls run at once, one request each; 0 for one per CPU core; an integer
            >= 0. A PyTorch policy predicts one call at a time whatever this says.
    """

    max_batch: int = 1
    batch_window_ms: float = 0.0
    prediction_threads: int = 0

    def __post_init__(self) -> None:
        _require(
            isinstance(self.max_batch, int) and not isinstance(self.max_batch, bool) and self.max_batch >= 1,
            "serving.max_batch",
            self.max_batch,
            "must be an integer >= 1",
        )
        _require(
            0 <= self.batch_window_ms <= 1000,
            "serving.batch_window_ms",
            self.batch_window_ms,
            "must be between 0 and 1000",
        )
        _require(
            isinstance(self.prediction_threads, int)
            and not isinstance(self.prediction_threads, bool)
            and self.prediction_threads >= 0,
            "serving.prediction_threads",
            self.prediction_threads,
            "must be an integer >= 0 (0: one per CPU core)",
        )
