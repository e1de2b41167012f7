"""Frames read and decoded on threads of their own, a few ahead of the pipeline.

Reading a 640x480 RGB-D pair (two image files decoded) takes milliseconds of host time, about
9 ms on the 2-core VM of docs/benchmarks.md: more than a GPU pipeline's whole frame. Read in
turn with the work, it adds to every frame; read ahead, it overlaps the frames before, since
OpenCV's decoders release the interpreter lock. Only the reading threads touch the sequence
while the frames are read, and `close` waits for them, so the sequence is the caller's again
afterwards. Where the sequence allows it (FrameSequence.parallel_reads: a TUM folder, whose
reads each open their own files), several threads (one per four cores) decode in parallel, each
its share of the indices, so that a GPU run is not bound by one thread's decoding.

Each item is (index, frame or the error that reading it raised), in index order: what to do
with an unreadable frame (stop, or skip and count it) stays with the caller, and happens when
the pipeline reaches that frame, not when the reader does.
"""

from __future__ import annotations

import itertools
import os
import queue
import threading
from collections.abc import Callable, Iterable, Iterator
from types import TracebackType
from typing import Any

# Frames read before the pipeline asks for them: enough to ride over one slow read, few enough
# that a stopped run has not read far past its last frame (4 pairs at 640x480: 6 MB).
READ_AHEAD = 4
# How often a blocked put or get looks again whether the other side has stopped (seconds).
POLL = 0.1

_DONE = object()  # the end of a reader's indices


def readers_for(cores: int | None = None) -> int:
    """Reading threads for a machine of `cores` cores (None: this one's): one per four cores,
    from one to four. A GPU pipeline leaves the host's cores idle and can take frames faster
    than one thread decodes them (about 10 ms a 640x480 pair on the 2-core VM); the cpu
    pipeline needs the cores itself, so a small machine keeps to one."""
    if cores is None:
        cores = os.cpu_count() or 1
    return max(1, min(4, cores // 4))


class ReadAhead:
    """`read(index)` for each of `indices`, on `readers` threads (index k on thread k mod
    readers), at most about `depth` items ahead, handed out in index order:

        with ReadAhead(sequence.__getitem__, range(start, stop)) as items:
            for index, frame, error in items: ...

    `error` is None or the exception `read` raised for that index (frame then None). Reading
    goes on after an error of the kinds `goes_on_after`; any other error is the last item.
    """

    def __init__(
        self,
        read: Callable[[int], Any],
        indices: Iterable[int],
        depth: int = READ_AHEAD,
        goes_on_after: type[BaseException] | tuple[type[BaseException], ...] = (),
        readers: int = 1,
    ) -> None:
        indices = list(indices)
        count = max(1, min(readers, len(indices)))
        self._read, self._goes_on_after = read, goes_on_after
        self._stop = threading.Event()
        self._queues = [queue.Queue(maxsize=max(1, depth // count)) for _ in range(count)]
        self._threads = [
            threading.Thread(
                target=self._run, args=(indices[k::count], self._queues[k]), daemon=True
            )
            for k in range(count)
        ]
        for thread in self._threads:
            thread.start()

    def __iter__(self) -> Iterator[tuple[int, Any, BaseException | None]]:
        for turn in itertools.count():
            k = turn % len(self._queues)
            item = self._get(k)
            if item is _DONE:
                return
            yield item
            if item[2] is not None and not isinstance(item[2], self._goes_on_after):
                return

    def _get(self, k: int) -> Any:
        while True:
            try:
                return self._queues[k].get(timeout=POLL)
            except queue.Empty:
                if not self._threads[k].is_alive() and self._queues[k].empty():
                    return _DONE

    def _run(self, indices: list[int], items: queue.Queue) -> None:
        for index in indices:
            if self._stop.is_set():
                return
            try:
                item = (index, self._read(index), None)
            except BaseException as error:  # handed to the caller, in order
                item = (index, None, error)
            if not self._put(items, item) or (
                item[2] is not None and not isinstance(item[2], self._goes_on_after)
            ):
                return
        self._put(items, _DONE)

    def _put(self, items: queue.Queue, item: Any) -> bool:
        """Queue `item`; False when the caller stopped first."""
        while not self._stop.is_set():
            try:
                items.put(item, timeout=POLL)
                return True
            except queue.Full:
                continue
        return False

    def alive(self) -> bool:
        """Whether a reading thread still runs."""
        return any(thread.is_alive() for thread in self._threads)

    def close(self) -> None:
        """Stop reading and wait for the threads (at most the reads in progress)."""
        self._stop.set()
        for thread in self._threads:
            thread.join()

    def __enter__(self) -> ReadAhead:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()
