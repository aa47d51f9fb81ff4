"""Prediction calls off the event loop: batched where the policy allows it, concurrent where its backend does.

The event loop hands each request that asks for a chunk to :meth:`PredictionQueue.predict` and awaits its row. One
worker takes the first waiting request and every other one already waiting (up to `max_batch_size`), and predicts
them in one call when they are answered by the same model and that model draws nothing random
(`ServedModel.batches`: each row then equals its prediction alone up to float rounding, see docs/serving.md for how
often a greedy token choice flips on it); otherwise one call each, in arrival order. With `batch_window_s` 0 nothing
waits for a batch to fill: a lone request is predicted at once, and batches form only from requests that arrived
while the previous call ran; a positive window lets the first request of a batching model wait that long for others.
A policy that samples keeps one call per request because each episode's draws come from its own generator, which a
batched call cannot honour.

A PyTorch model predicts one call at a time. A model whose backend runs calls concurrently (`ServedModel.concurrent`:
exported ONNX Runtime graphs, one request per call) gets up to `concurrent_calls` calls in flight on the executor's
threads, so that its throughput grows with the clients up to the CPU cores; each request is still predicted alone,
so its chunk equals the in-process prediction bit for bit.
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
    """Runs predictions on `executor`, batching the requests that wait together and overlapping concurrent calls.

    Args:
        executor: where calls run, off the event loop; it needs `concurrent_calls` threads.
        max_batch_size: most requests in one call; 1 predicts every request alone.
        on_call: called on the event loop after each successful call with the number of requests it answered.
        concurrent_calls: most calls in flight at once for a model that allows it (`ServedModel.concurrent`).
        batch_window_s: seconds the first waiting request of a batching model waits for others to join its call.
    """

    def __init__(
        self,
        executor: Executor,
        max_batch_size: int,
        on_call=lambda size: None,
        concurrent_calls: int = 1,
        batch_window_s: float = 0.0,
    ) -> None:
        if max_batch_size < 1:
            raise ValueError(f"max_batch_size must be >= 1, got {max_batch_size}")
        if concurrent_calls < 1:
            raise ValueError(f"concurrent_calls must be >= 1, got {concurrent_calls}")
        if batch_window_s < 0:
            raise ValueError(f"batch_window_s must be >= 0, got {batch_window_s}")
        self.executor = executor
        self.max_batch_size = max_batch_size
        self.on_call = on_call
        self.concurrent_calls = concurrent_calls
        self.batch_window_s = batch_window_s
        self._queue: asyncio.Queue[_Waiting] | None = None
        self._worker: asyncio.Task | None = None
        self._slots: asyncio.Semaphore | None = None
        self._in_flight: set[asyncio.Task] = set()

    def start(self) -> None:
        """Start the worker on the running event loop."""
        self._queue = asyncio.Queue()
        self._slots = asyncio.Semaphore(self.concurrent_calls)
        self._worker = asyncio.get_running_loop().create_task(self._run())

    async def stop(self) -> None:
        """Stop the worker and the calls in flight; requests still waiting are cancelled."""
        for task in [self._worker, *self._in_flight]:
            if task is None:
                continue
            task.cancel()
            try:
                await task
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
            if self.batch_window_s > 0 and waiting[0].model.batches and self.max_batch_size > 1:
                await self._gather(waiting)
            while not self._queue.empty():
                waiting.append(self._queue.get_nowait())
            for group in _calls(waiting, self.max_batch_size):
                await self._slots.acquire()
                if group[0].model.concurrent:
                    task = asyncio.get_running_loop().create_task(self._call(group))
                    self._in_flight.add(task)
                    task.add_done_callback(self._finished)
                else:
                    try:
                        await self._call(group)
                    finally:
                        self._slots.release()

    def _finished(self, task: asyncio.Task) -> None:
        self._in_flight.discard(task)
        self._slots.release()

    async def _gather(self, waiting: list[_Waiting]) -> None:
        """Add requests arriving within the batch window to `waiting`, until the window closes or a batch is full."""
        deadline = asyncio.get_running_loop().time() + self.batch_window_s
        while len(waiting) < self.max_batch_size:
            remaining = deadline - asyncio.get_running_loop().time()
            if remaining <= 0:
                return
            try:
                waiting.append(await asyncio.wait_for(self._queue.get(), remaining))
            except TimeoutError:
                return

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
