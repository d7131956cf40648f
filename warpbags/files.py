"""Atomic output files: a reader never sees a half-written checkpoint, PLY, table or report."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_output(path: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling of `path` to write; it replaces `path` when the block succeeds and is removed
    when it fails. The temporary keeps the suffix (`name.tmp.npy`), so writers that choose a format by extension
    (numpy, OpenCV's video writer) still work."""
    path = Path(path)
    temporary = path.with_name(f"{path.stem}.tmp{path.suffix}")
    try:
        yield temporary
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
