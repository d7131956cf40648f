"""`warpbags view RUN_OR_PLY`: a web viewer of the Gaussians and the training cameras (viser)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer
from rich.text import Text

from warpbags.cli.common import clean_errors, stdout


def view(
    path: Path = typer.Argument(..., help="Run folder, or a 3DGS gaussians.ply from any tool."),
    port: int = typer.Option(8080, "--port", help="TCP port (the next free one if it is busy)."),
    host: str = typer.Option("127.0.0.1", "--host", help="Interface to listen on (0.0.0.0: the whole network)."),
    device: Optional[str] = typer.Option(None, "--device", help="cpu or cuda (default: cuda when available)."),
) -> None:
    """Open a web viewer: the Gaussians rendered from your camera, the training cameras (start, optimized,
    reference) as frustums, and a slider over the run's pose history. Ctrl-C stops it."""
    from warpbags.viewer import Viewer, load_viewer_content  # noqa: PLC0415 - viser's import (0.4 s) only here

    content = load_viewer_content(path, log=stdout.print)
    viewer = Viewer(content, host=host, port=port, device=device)
    stdout.print(Text.assemble(("warpbags view", "bold"), f": {content.name} at ", (viewer.url, f"link {viewer.url}"),
                               "  (Ctrl-C stops)"))
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        stdout.print("viewer stopped")
    finally:
        viewer.stop()


def register(app: typer.Typer) -> None:
    """Add `view` to `app`."""
    app.command("view")(clean_errors(view))
