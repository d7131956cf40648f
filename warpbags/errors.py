"""The one exception type users see: bad input, described in a single line; and other exceptions in one line."""

import signal
import threading
from contextlib import contextmanager
from typing import Iterator


class WarpbagsError(Exception):
    """Bad input or an unusable file; the message names the offending file or value in one line.

    The CLI prints it without a traceback and exits non-zero; library users can catch it.
    """


def one_line(error: BaseException, limit: int = 200) -> str:
    """`error` as "Type: first line of its message", at most `limit` characters: what a one-line report of an
    exception from another library (a checkpoint torch cannot read, a metric package that will not import) says."""
    lines = str(error).splitlines()
    return f"{type(error).__name__}: {lines[0] if lines else ''}"[:limit]


class Stopped(KeyboardInterrupt):
    """Training stopped by a signal (Ctrl-C's SIGINT, or the SIGTERM of `kill` or a job scheduler) after saving a
    checkpoint. A KeyboardInterrupt, so what handles Ctrl-C handles it; `signum` says which signal, for the shell's
    exit status 128 + signum (130 for SIGINT, 143 for SIGTERM)."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum

    def __reduce__(self):  # rebuilt from the number, not the name its args hold (across Ray or multiprocessing)
        return Stopped, (self.signum,)


def raise_stopped(signum: int, frame) -> None:
    """A signal handler: the signal as Stopped, as Ctrl-C is a KeyboardInterrupt."""
    raise Stopped(signum)


def sigterm_unclaimed() -> bool:
    """Whether SIGTERM is still ours to take: its default (which ends the process at once) or `raise_stopped` (set by
    an enclosing `sigterm_stops`, which a block inside may replace with a handler that stops more gently, as the
    trainer's finishes its iteration and saves a checkpoint); never a handler of the caller's or of another library's
    (a Ray worker's exits so that Ray retries its task)."""
    handler = signal.getsignal(signal.SIGTERM)
    return handler == signal.SIG_DFL or handler is raise_stopped


@contextmanager
def sigterm_stops() -> Iterator[None]:
    """In the block, SIGTERM (`kill`, a job scheduler) raises Stopped as Ctrl-C raises KeyboardInterrupt, so that
    the block's cleanup runs (its default ends the process at once); only where no other handler takes it, and on
    the main thread, the one Python delivers signals to."""
    if threading.current_thread() is not threading.main_thread() or not sigterm_unclaimed():
        yield
        return

    previous = signal.signal(signal.SIGTERM, raise_stopped)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
