"""Output files: atomic (a reader never sees a half-written checkpoint, PLY, table or report), strict JSON, and
output folders checked before any work; NumPy arrays read with one line naming a file that is not one."""

from __future__ import annotations

import json
import math
import os
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np

from warpbags.errors import WarpbagsError, one_line


def temporary_name(name: str) -> str:
    """The name of `atomic_output`'s temporary for a file named `name` (`poses.npy` -> `poses.tmp.npy`): what a
    write cut short by a kill leaves behind."""
    path = Path(name)
    return f"{path.stem}.tmp{path.suffix}"


def is_temporary(path: str | Path) -> bool:
    """Whether `path` is named as an `atomic_output` temporary."""
    return Path(path).stem.endswith(".tmp")


@contextmanager
def atomic_output(path: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling of `path` to write (`temporary_name`); it replaces `path` when the block succeeds and
    is removed when it fails. The temporary keeps the suffix (`name.tmp.npy`), so writers that choose a format by
    extension (numpy, OpenCV's video writer) still work."""
    path = Path(path)
    temporary = path.with_name(temporary_name(path.name))
    try:
        yield temporary
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def writable_folder(path: str | Path, purpose: str) -> Path:
    """`path` as a folder that can be written (it exists as a folder, or can be made): checked before a command does
    any work, so a bad --out is one line, not a traceback after minutes of training.

    Raises:
        WarpbagsError: `path` or its nearest existing parent is a file, or that folder cannot be written;
            `purpose` says what the folder was for ("to train into").
    """
    path = Path(path)
    for existing in (path, *path.parents):
        if existing.is_symlink() and not existing.exists():  # `runs` linked to a disk that is not mounted
            raise WarpbagsError(f"{existing} is a link to {os.readlink(existing)}, which does not exist: no folder "
                                f"{purpose}")
        if existing.exists():
            if not existing.is_dir():
                raise WarpbagsError(f"{existing} is a file, not a folder {purpose}")
            if not os.access(existing, os.W_OK | os.X_OK):
                target = "" if existing == path else f", so {path} cannot be made"
                raise WarpbagsError(f"{existing} is not writable{target}: no folder {purpose}")
            break
    return path


def missing_folders(path: str | Path) -> list[Path]:
    """`path` and those of its parents that do not exist yet (deepest first): what making it makes, and what a
    failed write there should remove again."""
    path = Path(path)
    return [folder for folder in (path, *path.parents) if not folder.exists()]


def writable_file(path: str | Path, purpose: str) -> Path:
    """`path` as a file that can be written or replaced (it is missing or a file, and its folder exists or can be
    made): the sibling of `writable_folder` for the files a command writes, checked before it writes any of them.

    Raises:
        WarpbagsError: `path` is a folder, or its folder cannot be had (`writable_folder`); `purpose` says what the
            file was for ("to write the evaluation to").
    """
    path = Path(path)
    if path.is_dir():
        raise WarpbagsError(f"{path} is a folder, not a file {purpose}")
    writable_folder(path.parent, purpose)
    return path


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


def write_image(path: str | Path, pixels: np.ndarray) -> None:
    """Write uint8 `pixels` ([H, W] grey or [H, W, 3] BGR, as OpenCV takes them) to `path`, in the image format of its
    suffix. Python writes the encoded bytes and raises on a failed write (a full disk, a file-size limit); OpenCV's
    imwrite reports none and leaves a file cut short.

    Raises:
        WarpbagsError: OpenCV cannot encode the pixels in that format. OSError: the write failed.
    """
    path = Path(path)
    try:
        encoded, data = cv2.imencode(path.suffix, pixels)
    except cv2.error as error:  # no encoder for the suffix, pixels the format cannot hold
        raise WarpbagsError(f"OpenCV could not encode {path}: {one_line(error)}") from None
    if not encoded:
        raise WarpbagsError(f"OpenCV could not encode {path}")
    path.write_bytes(data.tobytes())


def read_array(path: Path, what: str) -> np.ndarray:
    """The real numbers in the .npy file `path` (no pickles), or one line naming it as `what`.

    Raises:
        WarpbagsError: unreadable, not a NumPy array file (empty or truncated: numpy's EOFError, which the command
            line turned into a bare "Aborted."; text; a pickle), or not real numbers.
    """
    try:
        array = np.load(path)
    except OSError as error:
        raise WarpbagsError(f"cannot read {what} {path}: {error.strerror or error}") from None
    except (ValueError, EOFError, zipfile.BadZipFile):  # an .npz cut short starts as a zip and reads as one
        raise WarpbagsError(f"{what} {path} is not a NumPy array file (empty, truncated, text or pickled)") from None
    if not isinstance(array, np.ndarray):  # an .npz archive under this name
        raise WarpbagsError(f"{what} {path} is an archive of arrays (.npz), not one NumPy array")
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise WarpbagsError(f"{what} {path} holds {array.dtype} values, expected real numbers")
    return array
