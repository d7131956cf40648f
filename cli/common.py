"""What every command module shares: bad input as one line on stderr and exit code 2, lists of numbers read."""

from __future__ import annotations

import functools
import math
import signal
import sys
from typing import Callable

from rich.console import Console
from rich.markup import escape

from warpbags.errors import Stopped, WarpbagsError, one_line

stderr = Console(stderr=True)
# every command's output: plain text, so that paths and names with brackets (`runs/mary[s0]`) are not Rich markup
stdout = Console(highlight=False, markup=False)


def clean_errors(command: Callable) -> Callable:
    """Turn a WarpbagsError into one red line on stderr and exit code 2, never a traceback."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except (WarpbagsError, OSError) as error:
            # a file a command could not write or read (a full disk, a file-size limit) is one line too
            message = str(error) if isinstance(error, WarpbagsError) else one_line(error)
            # escaped: a message's own brackets (`warpbags[ray]`, a list) are text, not Rich markup
            stderr.print(f"[bold red]error:[/] {escape(message)}", highlight=False, soft_wrap=True)
            sys.exit(2)
        except KeyboardInterrupt as interrupt:
            # the shell's convention, which job schedulers read: 128 + the signal (130 Ctrl-C, 143 SIGTERM)
            signum = interrupt.signum if isinstance(interrupt, Stopped) else signal.SIGINT
            stderr.print(f"[yellow]stopped by {signal.Signals(signum).name}[/]")
            sys.exit(128 + signum)

    return wrapper


def _shown(bound: float) -> str:
    """A bound as a message shows it: an integer whole (2^32 - 1 as 4294967295, not 4.29497e+09)."""
    return str(bound) if isinstance(bound, int) else f"{bound:g}"


def parse_numbers(text: str, option: str, kind: Callable = float, minimum: float | None = None,
                  maximum: float | None = None) -> list:
    """The comma-separated numbers of option `option` (empty items skipped): `kind` (float or int) of each.

    Raises:
        WarpbagsError: an item that is not a finite `kind` or is outside [`minimum`, `maximum`], or no number at all.
    """
    numbers = []
    for item in text.split(","):
        if not item.strip():
            continue
        try:
            if "_" in item:  # Python reads "4_6" as 46: a typo of "4,6" would run seed 46
                raise ValueError(item)
            numbers.append(kind(item))
        except ValueError:
            what = "an integer" if kind is int else "a number"
            raise WarpbagsError(f"{option} {text!r}: {item.strip()!r} is not {what}") from None
        if not math.isfinite(numbers[-1]):
            raise WarpbagsError(f"{option} {text!r}: {item.strip()!r} is not a finite number")
        if minimum is not None and numbers[-1] < minimum:
            raise WarpbagsError(f"{option} {text!r}: {item.strip()} is below {_shown(minimum)}")
        if maximum is not None and numbers[-1] > maximum:
            raise WarpbagsError(f"{option} {text!r}: {item.strip()} is above {_shown(maximum)}")
    if not numbers:
        raise WarpbagsError(f"{option} {text!r}: expected comma-separated numbers, got none")
    return numbers
