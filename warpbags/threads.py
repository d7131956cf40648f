"""Host threads beside Warp's: how many torch may use while Warp renders, and one side thread for work that can run
beside a render (`beside_render` for a differentiable term)."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Callable, Iterator

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


def beside_render(function: Callable[..., torch.Tensor], *args) -> Callable[[], torch.Tensor]:
    """Start `function(*args)`, a differentiable [] term, on the side thread; returns the call that waits for it
    and gives its value joined to the calling thread's graph by one node, made on the calling thread.

    Autograd walks a backward's ready nodes in the order of a sequence number that each thread counts for itself.
    A term whose nodes were made on the side thread and fed into the main graph was walked early or late depending
    on how many nodes each thread had made before, and a parameter that takes gradients from several paths (the
    Gaussian centres: the render and the silhouette chamfer) summed them in that order: a run resumed in a new
    process left the uninterrupted run at rounding level. Here the side thread differentiates detached copies of
    the tensors that need a gradient, and one node on the calling thread passes the gradients on to the originals.
    Only tensors passed as arguments themselves are followed (not inside lists, nor captured by `function`), and
    the term's gradient is first-order only.

    Raises:
        TypeError: a list, tuple or dict argument holds a tensor that needs a gradient (its gradient would be lost).
    """
    for arg in args:
        if isinstance(arg, (list, tuple, dict)) and any(
                isinstance(item, torch.Tensor) and item.requires_grad
                for item in (arg.values() if isinstance(arg, dict) else arg)):
            raise TypeError("beside_render follows tensors passed as arguments themselves, not inside containers")
    if not torch.is_grad_enabled():
        future = side_thread().submit(_without_grad, function, *args)
        return future.result
    tracked = [i for i, arg in enumerate(args) if isinstance(arg, torch.Tensor) and arg.requires_grad]
    side_args = list(args)
    for i in tracked:
        side_args[i] = args[i].detach().requires_grad_()
    future = side_thread().submit(function, *side_args)

    def joined() -> torch.Tensor:
        value = future.result()
        if not value.requires_grad:
            return value
        return _JoinedTerm.apply(_SideGraph(value, [side_args[i] for i in tracked]), *(args[i] for i in tracked))

    return joined


def _without_grad(function: Callable[..., torch.Tensor], *args) -> torch.Tensor:
    with torch.no_grad():
        return function(*args)


class _SideGraph:
    """A value and the leaves of the graph it was computed by (a plain holder: autograd does not follow it)."""

    def __init__(self, value: torch.Tensor, leaves: list[torch.Tensor]):
        self.value, self.leaves = value, leaves


class _JoinedTerm(torch.autograd.Function):
    """The side graph's value as one node of the calling thread's graph, its backward the side graph's."""

    @staticmethod
    def forward(ctx, side: _SideGraph, *inputs: torch.Tensor) -> torch.Tensor:
        ctx.side = side
        return side.value.detach()

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        side = ctx.side
        if torch.is_grad_enabled():  # a backward with create_graph: the side graph's gradients would be constants
            raise RuntimeError("a term computed beside the render has first derivatives only")
        if side is None:
            raise RuntimeError("a term computed beside the render is differentiated once (its side graph is freed)")
        gradients = torch.autograd.grad(side.value, side.leaves, grad, allow_unused=True)
        ctx.side = None  # the side graph is freed with its one backward
        return (None, *gradients)
