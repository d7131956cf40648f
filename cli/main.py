"""`warpbags` command-line entry point: parses options and calls the package, nothing more."""

from __future__ import annotations

import functools
import os
import sys
from typing import Callable

import typer
from rich.console import Console
from rich.markup import escape

from warpbags.errors import WarpbagsError

app = typer.Typer(
    name="warpbags",
    help="Bundle-Adjusting Gaussian Splatting with NVIDIA Warp kernels.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console(stderr=True)


@app.callback()
def configure(verbose: bool = typer.Option(False, "--verbose", help="Show Warp's own output: its banner, module "
                                           "loads and CUDA driver notes.")) -> None:
    """Bundle-Adjusting Gaussian Splatting with NVIDIA Warp kernels."""
    import warp as wp  # noqa: PLC0415 - only the command line silences Warp; library users keep its defaults

    if verbose:
        return
    wp.config.log_level = wp.LOG_WARNING  # no init banner or per-module load lines between the progress bars
    wp.config.quiet = True
    # On a machine without a CUDA driver Warp's native library prints a warning straight to file descriptor 2 when
    # it initializes; --device cuda without a driver is reported by warpbags itself.
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 2)
            wp.init()
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def clean_errors(command: Callable) -> Callable:
    """Turn a WarpbagsError into one red line on stderr and exit code 2, never a traceback."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except WarpbagsError as error:
            # escaped: a message's own brackets (`warpbags[ray]`, a list) are text, not Rich markup
            console.print(f"[bold red]error:[/] {escape(str(error))}", highlight=False, soft_wrap=True)
            sys.exit(2)
        except KeyboardInterrupt:
            console.print("[yellow]interrupted[/]")
            sys.exit(130)

    return wrapper


def main() -> None:
    app()


from warpbags.cli import info as _info  # noqa: E402,F401  registers `info` and `synth`
from warpbags.cli import train as _train  # noqa: E402,F401  registers `train`
from warpbags.cli import evaluate as _evaluate  # noqa: E402,F401  registers `eval`
from warpbags.cli import view as _view  # noqa: E402,F401  registers `view`
