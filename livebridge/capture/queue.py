"""The bounded queue between live stages: it keeps the newest items, so under load old ones are dropped.

Used by the camera drivers' grab threads, the synchroniser's frame-set hand-over and the pipeline's
outputs stage (DESIGN.md: queues between live stages are bounded and keep the newest item).
"""

from __future__ import annotations

import queue
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")


class NewestQueue(Generic[T]):
    """A bounded queue that keeps the newest items.

    :meth:`put` never blocks: when the queue is full it drops the oldest item (counted in ``dropped``).
    :meth:`put_waiting` is for unpaced producers (simulators, replays), which can wait for the consumer
    instead, so nothing is dropped.

    Parameters
    ----------
    maxsize : int
        Items kept.
    """

    def __init__(self, maxsize: int = 1):
        self._queue: queue.Queue[T] = queue.Queue(maxsize=maxsize)
        self.dropped = 0

    def put(self, item: T) -> None:
        """Add ``item``; when full, drop the oldest first."""
        while True:
            try:
                self._queue.put_nowait(item)
                return
            except queue.Full:
                try:
                    self._queue.get_nowait()
                    self.dropped += 1
                except queue.Empty:
                    pass

    def put_waiting(self, item: T, keep_waiting: Callable[[], bool], poll_s: float = 0.05) -> bool:
        """Wait for room and add ``item``, for as long as ``keep_waiting()`` is true (asked every ``poll_s``).

        Returns
        -------
        bool
            Whether ``item`` was added (False: ``keep_waiting()`` turned false first; nothing is dropped).
        """
        while keep_waiting():
            try:
                self._queue.put(item, timeout=poll_s)
                return True
            except queue.Full:
                continue
        return False

    def get(self, timeout: float | None = None) -> T | None:
        """The oldest item, or None after ``timeout`` seconds (None: wait for one) without any."""
        try:
            return self._queue.get(timeout=timeout)
        except queue.Empty:
            return None
