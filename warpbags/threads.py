"""Host threads beside Warp's: how many torch may use while Warp renders, and one side thread for work that can run
beside a render."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Iterator

import torch


def usable_cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


_HOST_THREAD_LIMIT: int | None = None


def host_threads() -> int:
    """Host threads for a CPU stage that is given no count (projection, binning, the fused loss, the coherence
    search, rendering without `cpu_threads`): the limit of `limited_host_threads` around the caller, else every
    usable core."""
    return _HOST_THREAD_LIMIT or usable_cores()


@contextmanager
def limited_host_threads(count: int | None) -> Iterator[None]:
    """Run the block with every CPU stage that is given no thread count on at most `count` host threads (None: no
    new limit), then restore the limit before it; a limit inside another never raises it.

    A process-wide setting, not a thread-local one, since the stages run on pool threads: a Ray task that declared
    `count` CPUs keeps to them, where its stages took every core of the machine beside the other tasks'. Enter it
    from one thread at a time (a sweep runs one task per worker process): blocks that overlap from several threads
    would restore each other's limits out of order."""
    global _HOST_THREAD_LIMIT  # noqa: PLW0603 - the one process-wide setting this module holds
    previous = _HOST_THREAD_LIMIT
    if count is not None:
        _HOST_THREAD_LIMIT = max(1, min(count, previous or usable_cores()))
    try:
        yield
    finally:
        _HOST_THREAD_LIMIT = previous


@contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """Run the block with torch limited to `count` intra-op threads, then give the caller back its setting.

    On the CPU, Warp runs its own host threads over the image; torch's idle OpenMP workers spin against them and
    take a core (measured 230 vs 146 ms for one step), so rendering code runs under `torch_threads(1)`.
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


_POOLS: dict[tuple[int, str, int], ThreadPoolExecutor] = {}


def thread_pool(name: str, workers: int) -> ThreadPoolExecutor:
    """This process's pool `name` of `workers` host threads, made once: a pool per call cost 2-8 ms of thread
    start-up and hand-over per rasterizer pass. Keyed by process id too, since a forked child inherits the pool
    object but not its threads."""
    key = (os.getpid(), name, workers)
    if key not in _POOLS:
        _POOLS[key] = ThreadPoolExecutor(max_workers=workers, thread_name_prefix=name)
    return _POOLS[key]


def side_thread() -> ThreadPoolExecutor:
    """One extra host thread, for work that can run beside the render (whose host threads leave a core idle between
    their stages); apart from the render's pool, so that neither waits for the other's threads."""
    return thread_pool("warpbags-side", 1)
