"""Output files: atomic (a reader never sees a half-written checkpoint, PLY, table or report) and strict JSON."""

from __future__ import annotations

import json
import math
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


def finite_json(value, indent: int | None = 2) -> str:
    """`value` as strict JSON: a float that is not finite (the PSNR of an exact render, a metric that failed) is
    written as null. Python's json writes NaN and Infinity, which other JSON readers reject, and calls a `default`
    hook only for types it cannot write, never for floats."""

    def finite(item):
        if isinstance(item, float):
            return item if math.isfinite(item) else None
        if isinstance(item, dict):
            return {key: finite(entry) for key, entry in item.items()}
        if isinstance(item, (list, tuple)):
            return [finite(entry) for entry in item]
        return item

    return json.dumps(finite(value), indent=indent, allow_nan=False)
