"""Per-frame work on several cores.

OpenCV and NumPy release Python's interpreter lock inside their calls, so a thread pool runs
per-frame work built on them (GrabCut, optical flow, colour conversion) side by side. The number
of workers is the process's torch thread count (``OMP_NUM_THREADS``, ``torch.set_num_threads``),
so one setting governs all of adnerf's parallelism; with one thread the work runs in the
caller's thread, as a plain loop.
"""

from __future__ import annotations

from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, Iterable, Iterator, TypeVar

__all__ = ["in_threads", "worker_count"]

T = TypeVar("T")
R = TypeVar("R")


def worker_count() -> int:
    """Threads adnerf's per-frame work may use: torch's intra-op thread count (at least one)."""
    import torch

    return max(1, int(torch.get_num_threads()))


def in_threads(fn: Callable[[T], R], items: Iterable[T], workers: int | None = None) -> Iterator[R]:
    """``fn`` of each item, computed on ``workers`` threads, yielded in the items' order.

    At most ``2 * workers`` results wait to be taken, so memory stays bounded however many items
    there are. An exception in ``fn`` is raised when its item's turn comes (later items already
    started are finished and dropped).

    Args:
        fn: The work of one item; it must not depend on the order items run in.
        items: The items.
        workers: Threads (default :func:`worker_count`); 1 runs ``fn`` in the calling thread.
    """
    workers = worker_count() if workers is None else max(1, int(workers))
    if workers == 1:
        yield from map(fn, items)
        return
    pending: deque[Future[R]] = deque()
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="adnerf") as pool:
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) >= 2 * workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
