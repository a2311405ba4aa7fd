"""Encoding off the render thread: :class:`EncodeLanes`, the engine's encode pool (setting ``encode_threads``).

After a batched render, the render thread hands each frame to its encoder's *lane* and goes on with the next
batch; ``threads`` workers encode the frames of different lanes in parallel (simplejpeg and PyAV release the GIL).
A lane is one encoder's queue (one per session, as the H.264 encoder is stateful): its work runs one item at a
time, in the order it was submitted, so an encoder never encodes two frames at once or out of order, and each
item's result is handed to its ``done`` callback before the next item starts (the engine's callbacks post to the
event loop, so a session's frames are delivered in order). A lane that empties is forgotten; no worker waits on
another. Closing an encoder (:meth:`EncodeLanes.close`) is an item of its lane: it runs after every frame submitted
before it.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

log = logging.getLogger(__name__)

Work = Callable[[], Any]
Done = Callable[[Any], None]


class EncodeLanes:
    """``threads`` encode workers, and one lane (a FIFO run one item at a time) per key (an encoder)."""

    def __init__(self, threads: int):
        self._pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="encode")
        self._lanes: dict[object, deque[tuple[Work, Done | None]]] = {}
        self._lock = threading.Lock()

    def submit(self, key: object, work: Work, done: Done | None = None) -> None:
        """Run ``work()`` in ``key``'s lane, after the work submitted to it before; ``done`` gets its result (or
        the exception it raised) on the worker, before the lane's next item starts. Any thread may submit;
        RuntimeError once :meth:`shutdown` began."""
        with self._lock:
            lane = self._lanes.get(key)
            if lane is not None:  # a worker is running this lane: it takes the item in its turn
                lane.append((work, done))
                return
            self._lanes[key] = deque([(work, done)])
            try:
                self._pool.submit(self._run, key)
            except RuntimeError:
                del self._lanes[key]
                raise

    def close(self, encoder: Any) -> None:
        """``encoder.close()`` in its lane: after every frame of it submitted so far (the caller's thread when the
        pool is shut down: nothing encodes any more)."""
        try:
            self.submit(encoder, encoder.close)
        except RuntimeError:
            encoder.close()

    def shutdown(self) -> None:
        """Take no more work; return once every item submitted has run (their ``done`` callbacks included)."""
        self._pool.shutdown(wait=True)

    @property
    def busy(self) -> int:
        """Lanes with work queued or running."""
        with self._lock:
            return len(self._lanes)

    def _run(self, key: object) -> None:
        """A worker's turn at one lane: its items, in order, until it is empty (then the lane is forgotten)."""
        while True:
            with self._lock:
                lane = self._lanes[key]
                if not lane:
                    del self._lanes[key]
                    return
                work, done = lane.popleft()
            try:
                result = work()
            except Exception as e:  # noqa: BLE001 - handed to done, as the work's result
                result = e
            if done is not None:
                try:
                    done(result)
                except Exception:  # a callback's failure must not stop the lane (the items after it)
                    log.exception("an encode lane's callback failed")
