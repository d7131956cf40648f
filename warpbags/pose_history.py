"""The training cameras' poses every few iterations, kept in the run folder so `warpbags view` can replay them.

`poses_history.npz` holds `iterations` [T] (int64, increasing) and `viewmats` [T,C,4,4] (float32, world-to-camera,
OpenCV axes, the trainer's current estimate at each of those iterations). Each record rewrites the file atomically
(temp + rename), so a viewer or a crash never sees half a file; at ~64 bytes per camera a record, thousands of
records stay small.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from warpbags.errors import WarpbagsError, one_line
from warpbags.files import atomic_output

HISTORY_FILE = "poses_history.npz"
RECORD_EVERY = 10  # iterations between records: 60 frames over the quick preset's 600 iterations


@dataclass
class PoseHistory:
    """Recorded poses of the C training cameras.

    Attributes:
        iterations: [T] the iteration of each record, increasing.
        viewmats: [T,C,4,4] world-to-camera matrices at those iterations.
    """

    iterations: np.ndarray
    viewmats: np.ndarray


def read_pose_history(run_dir: str | Path) -> PoseHistory | None:
    """The run's pose history, or None when it recorded none.

    Raises:
        WarpbagsError: the file exists but cannot be read.
    """
    path = Path(run_dir) / HISTORY_FILE
    if not path.is_file():
        return None
    try:
        with np.load(path) as stored:
            history = PoseHistory(stored["iterations"].astype(np.int64), stored["viewmats"].astype(np.float32))
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, AttributeError, TypeError,
            NotImplementedError) as error:
        # empty, not a zip archive, not an .npz of arrays (an .npy under its name), scalars, a damaged compression
        # method (zipfile: "That compression method is not supported"). numpy takes a file that is no archive for
        # pickled data and advises `allow_pickle=True`, which would run what the file holds: not repeated here.
        reason = "not an .npz archive" if "allow_pickle" in str(error) else one_line(error)
        raise WarpbagsError(f"{path}: unreadable pose history ({reason})") from None
    shape = history.viewmats.shape
    if history.iterations.ndim != 1 or len(shape) != 4 or shape != (len(history.iterations), shape[1], 4, 4):
        raise WarpbagsError(f"{path}: iterations of shape {list(history.iterations.shape)} and viewmats of shape "
                            f"{list(shape)}, expected [T] and [T,C,4,4]")
    return history


def record_poses(run_dir: str | Path, iteration: int, viewmats: torch.Tensor | np.ndarray) -> None:
    """Append the poses at `iteration` to the run's history.

    Records at or after `iteration` are dropped first: a run resumed from an earlier checkpoint replays those
    iterations, and its history must follow the resumed trajectory (as log.jsonl is cut back).

    Args:
        run_dir: the run folder.
        iteration: the training iteration the poses belong to.
        viewmats: [C,4,4] world-to-camera matrices (any device and float dtype).

    Raises:
        WarpbagsError: the camera count differs from the recorded one.
    """
    if isinstance(viewmats, torch.Tensor):
        viewmats = viewmats.detach().cpu().numpy()
    viewmats = np.asarray(viewmats, dtype=np.float32)[None]
    history = read_pose_history(run_dir)
    iterations = np.array([iteration], dtype=np.int64)
    if history is not None:
        if history.viewmats.shape[1:] != viewmats.shape[1:]:
            raise WarpbagsError(f"{Path(run_dir) / HISTORY_FILE} holds {history.viewmats.shape[1]} cameras, "
                                f"got {viewmats.shape[1]}")
        kept = history.iterations < iteration
        iterations = np.concatenate([history.iterations[kept], iterations])
        viewmats = np.concatenate([history.viewmats[kept], viewmats])
    with atomic_output(Path(run_dir) / HISTORY_FILE) as temporary:
        np.savez(temporary, iterations=iterations, viewmats=viewmats)
