"""`warpbags` command-line entry point: parses options and calls the package, nothing more.

Each module of COMMAND_GROUPS holds one group of commands and adds them to the app with its `register(app)`.
"""

from __future__ import annotations

import os
import sys

import typer

from warpbags.cli import evaluate, export, info, sweep, train, view

# In `warpbags --help` order: info, synth, train, eval, export, render, sweep, view.
COMMAND_GROUPS = (info, train, evaluate, export, sweep, view)


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


def build_app() -> typer.Typer:
    """The `warpbags` app: the --verbose callback and every command of COMMAND_GROUPS."""
    app = typer.Typer(
        name="warpbags",
        help="Bundle-Adjusting Gaussian Splatting with NVIDIA Warp kernels.",
        no_args_is_help=True,
        add_completion=False,
        pretty_exceptions_enable=False,
        rich_markup_mode="rich",  # help texts are Rich markup: brackets meant as text are escaped
    )
    app.callback()(configure)
    for group in COMMAND_GROUPS:
        group.register(app)
    return app


app = build_app()


def main() -> None:
    app()


if __name__ == "__main__":
    main()
