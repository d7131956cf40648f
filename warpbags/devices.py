"""The one check of a `--device` value (the name, and on request whether torch can use it here), and Warp initialized
without its own output for the command line and the benchmarks."""

from __future__ import annotations

import os
import sys

import torch

from warpbags.errors import WarpbagsError

DEVICES = ("cpu", "cuda")


def checked_device_name(name: str) -> str:
    """`name` when it is "cpu" or "cuda" (a sweep checks only this much: its runs may go to other machines).

    Raises:
        WarpbagsError: any other name.
    """
    if name not in DEVICES:
        raise WarpbagsError(f"--device must be cpu or cuda, got {name!r}")
    return name


def torch_device(name: str | None = None) -> torch.device:
    """The torch device `name` names, usable on this machine; None: CUDA when available, else the CPU.

    Raises:
        WarpbagsError: an unknown name, or cuda without a CUDA device.
    """
    if name is None:
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if checked_device_name(name) == "cuda" and not torch.cuda.is_available():
        raise WarpbagsError("--device cuda: no CUDA device is available")
    return torch.device(name)


def init_warp_quietly() -> None:
    """Initialize Warp without its banner, per-module load lines and, on a machine without a CUDA driver, the
    warning its native library prints straight to file descriptor 2 (`--device cuda` without a driver is reported by
    warpbags itself). For the command line and the benchmarks, whose output is their own; library users keep
    Warp's defaults."""
    import warp as wp  # noqa: PLC0415

    wp.config.log_level = wp.LOG_WARNING
    wp.config.quiet = True
    if sys.stderr is None:  # descriptor 2 closed (a daemon, `2>&-`): nothing to silence, and nothing to dup
        wp.init()
        return
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 2)
            wp.init()
    finally:
        os.dup2(saved, 2)
        os.close(saved)
