"""One prediction call at a time, on one thread; requests that wait meanwhile share the next call where they may.

The event loop hands each request that asks for a chunk to :meth:`PredictionQueue.predict` and awaits its row. One
worker takes the first waiting request and every other one already waiting (up to `max_batch_size`), and predicts
them in one call when they are answered by the same model and that model draws nothing random
(`ServedModel.batches`: each row then equals its prediction alone, up to float rounding); otherwise one call each,
in arrival order. Nothing waits for a batch to fill: a lone request is predicted at once, and batches form only from
requests that arrived while the previous call ran. A policy that samples keeps one call per request because each
episode's draws come from its own generator, which a batched call cannot honour.
"""

import asyncio
import logging
import time
from concurrent.futures import Executor
from dataclasses import dataclass

import numpy as np

from carp.serving.model import ServedModel
from carp.serving.session import Observed

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Prediction:
    """One request's chunk and when its call ran.

    Attributes:
        actions: (H, A) float32, the request's row of the call.
        encoding_seconds: the call's observation encoding time.
        started: `time.perf_counter()` when the call began (after any lock wait).
        finished: `time.perf_counter()` when the call returned.
        batch_size: requests the call answered.
    """

    actions: np.ndarray
    encoding_seconds: float
    started: float
    finished: float
    batch_size: int


@dataclass
class _Waiting:
    model: ServedModel
    observed: Observed
    future: asyncio.Future


class PredictionQueue:
    """Serializes predictions on `executor` (one thread) and batches the requests that wait together.

    Args:
        executor: where calls run, off the event loop.
        max_batch_size: most requests in one call; 1 predicts every request alone.
        on_call: called on the event loop after each successful call with the number of requests it answered.
    """

    def __init__(self, executor: Executor, max_batch_size: int, on_call=lambda size: None) -> None:
        if max_batch_size < 1:
            raise ValueError(f"max_batch_size must be >= 1, got {max_batch_size}")
        self.executor = executor
        self.max_batch_size = max_batch_size
        self.on_call = on_call
        self._queue: asyncio.Queue[_Waiting] | None = None
        self._worker: asyncio.Task | None = None

    def start(self) -> None:
        """Start the worker on the running event loop."""
        self._queue = asyncio.Queue()
        self._worker = asyncio.get_running_loop().create_task(self._run())

    async def stop(self) -> None:
        """Stop the worker; requests still waiting are cancelled."""
        if self._worker is not None:
            self._worker.cancel()
            try:
                await self._worker
            except asyncio.CancelledError:
                pass
        while self._queue is not None and not self._queue.empty():
            self._queue.get_nowait().future.cancel()

    async def predict(self, model: ServedModel, observed: Observed) -> Prediction:
        """The chunk `model` predicts for `observed`, once its turn comes.

        Raises:
            Exception: whatever the policy raised.
        """
        future = asyncio.get_running_loop().create_future()
        self._queue.put_nowait(_Waiting(model, observed, future))
        return await future

    async def _run(self) -> None:
        while True:
            waiting = [await self._queue.get()]
            while not self._queue.empty():
                waiting.append(self._queue.get_nowait())
            for group in _calls(waiting, self.max_batch_size):
                await self._call(group)

    async def _call(self, group: list[_Waiting]) -> None:
        group = [item for item in group if not item.future.cancelled()]  # their connections have gone
        if not group:
            return
        model = group[0].model
        loop = asyncio.get_running_loop()
        try:
            if len(group) == 1:
                timed, waited, started, finished = await loop.run_in_executor(
                    self.executor, _timed, model.predict, group[0].observed
                )
            else:
                batch = [item.observed for item in group]
                timed, waited, started, finished = await loop.run_in_executor(
                    self.executor, _timed, model.predict_batch, batch
                )
        except Exception as error:  # noqa: BLE001 - each request's awaiter decides what its client is told
            for item in group:
                if not item.future.done():
                    item.future.set_exception(error)
            return
        self.on_call(len(group))
        for row, item in enumerate(group):
            if not item.future.done():
                item.future.set_result(
                    Prediction(timed.actions[row], timed.encoding_seconds, started + waited, finished, len(group))
                )


def _timed(predict, argument):
    started = time.perf_counter()
    timed, waited = predict(argument)
    return timed, waited, started, time.perf_counter()


def _calls(waiting: list[_Waiting], max_batch_size: int) -> list[list[_Waiting]]:
    """Split requests in arrival order into calls: runs of one batching model, at most `max_batch_size` each."""
    calls: list[list[_Waiting]] = []
    for item in waiting:
        previous = calls[-1] if calls else None
        if (
            previous is not None
            and previous[0].model is item.model
            and item.model.batches
            and len(previous) < max_batch_size
        ):
            previous.append(item)
        else:
            calls.append([item])
    return calls
