"""`warpbags` command-line entry point: parses options and calls the package, nothing more.

Each module of COMMAND_GROUPS holds one group of commands and adds them to the app with its `register(app)`.
"""

from __future__ import annotations

import typer

from warpbags.cli import evaluate, export, info, sweep, train, view
from warpbags.devices import init_warp_quietly

# In `warpbags --help` order: info, synth, train, eval, agree, export, render, sweep, view.
COMMAND_GROUPS = (info, train, evaluate, export, sweep, view)


def configure(verbose: bool = typer.Option(False, "--verbose", help="Show Warp's own output: its banner, module "
                                           "loads and CUDA driver notes.")) -> None:
    """Bundle-Adjusting Gaussian Splatting with NVIDIA Warp kernels."""
    if not verbose:  # only the command line silences Warp; library users keep its defaults
        init_warp_quietly()


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
