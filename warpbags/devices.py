"""The one check of a `--device` value: the name, and on request whether torch can use it here."""

from __future__ import annotations

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
