"""Read ahead in a background thread: the next frames are decoded while the detector runs on the current ones.

    with Prefetcher(recording.frames(), size=4) as frames:
        for frame in frames:              # the same items, in the same order
            ...
    frames.waited                         # seconds the consumer spent waiting for an item

The queue is bounded (``size`` items), so memory holds at most ``size`` frames ahead. An exception raised while
reading (e.g. a ``RecordingError`` on a corrupt frame) is raised in the consumer at the position it occurred, after
the items read before it. Closing (leaving the ``with`` block, or ``close()``) stops the thread and closes the source
iterator in that thread, so a video capture is released even when the consumer stops early.
"""
from __future__ import annotations

import queue
import threading
import time
from typing import Iterable, Iterator

_END = object()


class _Failure:
    __slots__ = ("error",)

    def __init__(self, error: BaseException):
        self.error = error


class Prefetcher:
    """Iterate ``source`` in a daemon thread, up to ``size`` (>= 1) items ahead; ``prepare(item)``, when given, is
    applied to each item in that thread (e.g. copying a frame into pinned memory)."""

    def __init__(self, source: Iterable, size: int = 2, prepare=None):
        if size < 1:
            raise ValueError("size must be >= 1")
        self._source = iter(source)
        self._prepare = prepare
        self._queue: queue.Queue = queue.Queue(maxsize=size)
        self._stop = threading.Event()
        self._done = False
        self.waited = 0.0
        self._thread = threading.Thread(target=self._work, name="massviz-prefetch", daemon=True)
        self._thread.start()

    def _put(self, item) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def _work(self) -> None:
        try:
            for item in self._source:
                if self._prepare is not None:
                    item = self._prepare(item)
                if not self._put(item):
                    break
            else:
                self._put(_END)
        except BaseException as err:  # noqa: BLE001 - handed to the consumer, raised there
            self._put(_Failure(err))
        finally:
            close = getattr(self._source, "close", None)
            if close is not None:
                try:
                    close()
                except Exception:  # noqa: BLE001 - closing is best effort; the read error (if any) is reported
                    pass

    def __iter__(self) -> Iterator:
        return self

    def __next__(self):
        if self._done:
            raise StopIteration
        t0 = time.perf_counter()
        item = self._queue.get()
        self.waited += time.perf_counter() - t0
        if item is _END:
            self._done = True
            self._thread.join()
            raise StopIteration
        if isinstance(item, _Failure):
            self._done = True
            self._thread.join()
            raise item.error
        return item

    def close(self) -> None:
        """Stop reading ahead and wait for the thread to end (the source is closed in it)."""
        self._done = True
        self._stop.set()
        while self._thread.is_alive():
            try:  # unblock a put waiting on a full queue
                self._queue.get_nowait()
            except queue.Empty:
                pass
            self._thread.join(timeout=0.05)

    def __enter__(self) -> "Prefetcher":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["Prefetcher"]
