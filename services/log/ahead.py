"""Reading ahead: a recording read on its own thread, a bounded number of messages ahead of its consumer.

Decompressing a chunk (zstd) releases the GIL, and so do the estimation's kernels: with the file read on
a thread of its own, the next chunks are decompressed while the consumer estimates.  The thread holds at
most ``depth`` batches of ``batch`` items, whatever the file's length; an exception it meets is raised
in the consumer, in order, after the items read before it; and a consumer that stops early stops it.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator
from typing import Generic, TypeVar

__all__ = ["ReadAhead"]

T = TypeVar("T")

_END = object()


class ReadAhead(Generic[T]):
    """Iterate ``source`` on a thread of its own, at most ``depth`` × ``batch`` items ahead.

    Use as a context manager, and iterate it once::

        with ReadAhead(iter_payloads(path)) as payloads:
            for rec in payloads:
                ...

    The items come in ``source``'s order.  An exception raised by ``source`` is raised by the
    iteration once the items before it are consumed.  Leaving the ``with`` block (the iteration
    done, or abandoned by an exception of the consumer) stops the thread and closes ``source``,
    on the thread that iterates it.

    Parameters
    ----------
    source : iterable
    depth : int
        Batches held at most between the thread and the consumer.
    batch : int
        Items handed over at once (one lock round-trip and one wake-up per batch, not per item).
    """

    def __init__(self, source: Iterable[T], *, depth: int = 4, batch: int = 16) -> None:
        if depth < 1 or batch < 1:
            raise ValueError(f"ReadAhead depth and batch must be >= 1, got {depth} and {batch}")
        self._source = source
        self._batch = batch
        self._queue: queue.Queue[tuple[list[T], BaseException | None, bool]] = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="read-ahead", daemon=True)
        self._started = False

    def __enter__(self) -> ReadAhead[T]:
        self._thread.start()
        self._started = True
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        """Stop the thread (it closes ``source``) and wait for it."""
        self._stop.set()
        if not self._started:
            return
        while self._thread.is_alive():
            try:  # make room, so that a thread blocked on a full queue sees the stop
                self._queue.get(timeout=0.05)
            except queue.Empty:
                pass
        self._thread.join()

    def _run(self) -> None:
        items: list[T] = []
        error: BaseException | None = None
        try:
            it = iter(self._source)
            try:
                for item in it:
                    if self._stop.is_set():
                        return
                    items.append(item)
                    if len(items) >= self._batch:
                        if not self._hand_over(items, None, False):
                            return
                        items = []
            finally:
                close = getattr(it, "close", None)
                if close is not None:
                    close()
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, which raises it
            error = exc
        self._hand_over(items, error, True)

    def _hand_over(self, items: list[T], error: BaseException | None, last: bool) -> bool:
        """Queue a batch, waiting for room while the consumer has not stopped; False once it has."""
        while not self._stop.is_set():
            try:
                self._queue.put((items, error, last), timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def __iter__(self) -> Iterator[T]:
        if not self._started:
            raise RuntimeError("ReadAhead is iterated inside its with block")
        while True:
            items, error, last = self._queue.get()
            yield from items
            if last:
                self._thread.join()
                if error is not None:
                    raise error
                return
