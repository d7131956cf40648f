"""`RunFolder`: the files of a training run, the one place that writes them; `load_run` reads a finished one.

Layout:
    config.json        the resolved TrainConfig plus scene/view information
    poses_true.npy     [C,4,4] world-to-camera poses of the training views (normalized scene world)
    poses_init.npy     [C,4,4] the (noisy) poses given to training
    poses_start.npy    [C,4,4] the poses the optimization starts from (after the mask-centroid start, if used)
    intrinsics.npy     [C,3,3] the training views' intrinsics at the training resolution
    log.jsonl          one JSON object per iteration (its "iter" is the count of iterations done)
    poses_history.npz  the poses every RECORD_EVERY (10) iterations, for `warpbags view`: `iterations` [T] int64,
                       increasing, and `viewmats` [T,C,4,4] float32 world-to-camera (the camera optimizer's estimate
                       after that many iterations); rewritten atomically at each record (`warpbags.pose_history`
                       writes and reads it)
    checkpoints/       checkpoint_XXXXXX.pt, written atomically (temp file + os.replace); the newest 3 kept
    gaussians.ply      final Gaussians, standard 3DGS PLY layout
    poses_final.npy    [C,4,4] optimized world-to-camera poses (the camera optimizer's corrections of poses_start)
    coarse/            with a repair stage: the coarse stage's result as a run folder of its own (same files but
                       log and checkpoints), so `warpbags eval RUN/coarse` measures what repair changed
    repair/            the repair stage's pairs, repairer and sample pictures (see `warpbags.repair.stage`)

A checkpoint is a dict with the keys of `CHECKPOINT_KEYS` and "repair" (what `warpbags.trainer.Trainer` saves);
resuming cuts log.jsonl and the pose history back to the checkpoint's iteration (the history then ends with the
checkpoint's poses), so both describe the trajectory that led to it.
"""

from __future__ import annotations

import json
import pickle
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from warpbags.configs.train import TrainConfig
from warpbags.data.scene import Scene
from warpbags.errors import WarpbagsError, one_line
from warpbags.files import atomic_output
from warpbags.gaussians import read_ply, write_ply
from warpbags.pose_history import HISTORY_FILE, RECORD_EVERY, record_poses

CHECKPOINTS_KEPT = 3
# What a checkpoint must hold to be resumed; it also holds "repair" (the repair stage's state, or None).
CHECKPOINT_KEYS = ("iteration", "config", "params", "optimizer", "strategy", "cameras", "generator", "viewmats_init",
                   "viewmats_start")
LOG_FILE = "log.jsonl"


class RunFolder:
    """A run folder at `path` (created when first written)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.checkpoints = self.path / "checkpoints"

    # ----------------------------------------------------------------------------------------------- setup, results
    def write_setup(self, config: TrainConfig, scene: Scene, device: str, viewmats_true: torch.Tensor,
                    viewmats_init: torch.Tensor, viewmats_start: torch.Tensor) -> None:
        """config.json, poses_true/init/start.npy and intrinsics.npy, each written atomically.

        Args:
            scene: the training views at the full training resolution (their intrinsics are saved).
            viewmats_true, viewmats_init, viewmats_start: [C,4,4] world-to-camera.
        """
        self.path.mkdir(parents=True, exist_ok=True)
        info = {"config": config.to_dict(), "scene": scene.name, "image_names": scene.image_names,
                "scene_root": _root_of(scene), "resolution": scene.resolution,
                "normalization": scene.normalization.to_dict(),
                "width": scene.width, "height": scene.height, "device": device}
        with atomic_output(self.path / "config.json") as temporary:
            temporary.write_text(json.dumps(info, indent=2))
        for name, array in (("poses_true", viewmats_true), ("poses_init", viewmats_init),
                            ("poses_start", viewmats_start), ("intrinsics", scene.Ks)):
            with atomic_output(self.path / f"{name}.npy") as temporary:
                np.save(temporary, array.cpu().numpy())

    def read_info(self) -> dict:
        """config.json: the TrainConfig (under "config") and the scene and view information written with it.

        Raises:
            WarpbagsError: no config.json, or one that cannot be read.
        """
        path = self.path / "config.json"
        try:
            return json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as error:
            raise WarpbagsError(f"{path}: unreadable ({error})") from None

    def saved_config(self, info: dict | None = None) -> TrainConfig:
        """The TrainConfig in config.json (or in `info`, config.json already read).

        Raises:
            WarpbagsError: no config.json, or one that cannot be read.
        """
        info = self.read_info() if info is None else info
        try:
            return TrainConfig.from_dict(info["config"])
        except (KeyError, TypeError) as error:
            raise WarpbagsError(f"{self.path / 'config.json'}: unreadable ({error})") from None

    def trained_on(self, scene: Scene, info: dict | None = None) -> bool:
        """Whether the run here trained on `scene`'s folder (config.json's, or `info`'s, scene_root)."""
        info = self.read_info() if info is None else info
        return info.get("scene_root") == _root_of(scene)

    def read_array(self, name: str) -> np.ndarray | None:
        """`name`.npy ([C,4,4] poses, or [C,3,3] intrinsics) as float64, None when the run has none.

        Raises:
            WarpbagsError: the file exists but cannot be read.
        """
        path = self.path / f"{name}.npy"
        if not path.is_file():
            return None
        try:
            return np.load(path).astype(np.float64)
        except (OSError, ValueError) as error:
            raise WarpbagsError(f"{path}: unreadable ({error})") from None

    def write_results(self, params: dict[str, torch.Tensor], viewmats: torch.Tensor) -> None:
        """gaussians.ply and poses_final.npy ([C,4,4] world-to-camera)."""
        write_ply(self.path / "gaussians.ply", params)
        with atomic_output(self.path / "poses_final.npy") as temporary:
            np.save(temporary, viewmats.cpu().numpy())

    # ----------------------------------------------------------------------------------------------- log
    @contextmanager
    def log_writer(self) -> Iterator[Callable[[dict], None]]:
        """A function appending one record to log.jsonl (flushed at once), open for the block."""
        self.path.mkdir(parents=True, exist_ok=True)
        with open(self.path / LOG_FILE, "a") as log_file:
            def write(record: dict) -> None:
                log_file.write(json.dumps(record) + "\n")
                log_file.flush()

            yield write

    def read_log(self) -> list[dict]:
        """The per-iteration records of log.jsonl ([] without one)."""
        path = self.path / LOG_FILE
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.is_file() else []

    def record_poses(self, iteration: int, viewmats: torch.Tensor) -> None:
        """Append [C,4,4] `viewmats` to the pose history when `iteration` is a multiple of RECORD_EVERY."""
        if iteration % RECORD_EVERY == 0:
            record_poses(self.path, iteration, viewmats)

    def truncate(self, iteration: int, viewmats: torch.Tensor) -> None:
        """Drop what was logged after `iteration` (a resumed run replays those iterations): log.jsonl lines (and a
        line cut short by a crash) and pose-history records; the history then ends with [C,4,4] `viewmats`, the
        poses at `iteration`."""
        path = self.path / LOG_FILE
        if path.exists():
            kept = []
            for line in path.read_text().splitlines():
                try:
                    if json.loads(line)["iter"] <= iteration:
                        kept.append(line)
                except (json.JSONDecodeError, KeyError, TypeError):
                    continue
            with atomic_output(path) as temporary:
                temporary.write_text("".join(line + "\n" for line in kept))
        if (self.path / HISTORY_FILE).exists():
            record_poses(self.path, iteration, viewmats)  # records at or after `iteration` are replaced

    # ----------------------------------------------------------------------------------------------- checkpoints
    def has_checkpoint(self) -> bool:
        return self.latest_checkpoint() is not None

    def latest_checkpoint(self) -> Path | None:
        found = sorted(self.checkpoints.glob("checkpoint_*.pt"))
        return found[-1] if found else None

    def save_checkpoint(self, state: dict) -> Path:
        """Write `state` (the keys of CHECKPOINT_KEYS and "repair") atomically as checkpoint_<iteration>.pt; keep
        the newest CHECKPOINTS_KEPT."""
        missing = [key for key in CHECKPOINT_KEYS if key not in state]
        if missing:
            raise ValueError(f"checkpoint state lacks {missing}")
        self.checkpoints.mkdir(parents=True, exist_ok=True)
        path = self.checkpoints / f"checkpoint_{state['iteration']:06d}.pt"
        with atomic_output(path) as temporary:
            torch.save(state, temporary)
        for old in sorted(self.checkpoints.glob("checkpoint_*.pt"))[:-CHECKPOINTS_KEPT]:
            old.unlink()
        return path

    def load_checkpoint(self, path: Path, device: torch.device | str) -> dict:
        """The state saved in `path`, tensors on `device`.

        Raises:
            WarpbagsError: the file cannot be read, or an older warpbags wrote it (keys missing).
        """
        try:
            state = torch.load(path, map_location=device, weights_only=False)
        except (OSError, RuntimeError, EOFError, ValueError, pickle.UnpicklingError) as error:
            raise WarpbagsError(f"{path}: unreadable checkpoint ({one_line(error, limit=1000)})") from None
        missing = [key for key in CHECKPOINT_KEYS if not isinstance(state, dict) or key not in state]
        if missing:
            raise WarpbagsError(f"{path} was written by an older warpbags (no {', '.join(missing)}); it cannot be "
                                "resumed, start a new run")
        return state


def _root_of(scene: Scene) -> str:
    """A scene's folder as a run records it: absolute, links resolved."""
    return str(Path(scene.root).resolve())


@dataclass
class TrainingRun:
    """What a finished run folder holds (see `warpbags.run_folder` for the layout)."""

    path: Path
    info: dict
    config: TrainConfig
    params: dict[str, torch.Tensor]
    poses_true: torch.Tensor
    poses_init: torch.Tensor
    poses_final: torch.Tensor
    intrinsics: torch.Tensor | None  # [C,3,3] at the training resolution; None in runs of an older warpbags


def require_info(run: TrainingRun, *keys: str) -> None:
    """Raise WarpbagsError naming the run's config.json if it lacks one of `keys` (a run of an older warpbags)."""
    for key in keys:
        if key not in run.info:
            raise WarpbagsError(f"{run.path / 'config.json'} has no {key!r}: written by an older warpbags")


def latest_run(root: str | Path = "runs") -> Path:
    """The most recently modified run folder under `root` that holds a config.json.

    Raises:
        WarpbagsError: no run there.
    """
    runs = [p.parent for p in Path(root).glob("*/config.json")]
    if not runs:
        raise WarpbagsError(f"no training run under {Path(root).resolve()}; pass RUN_DIR or train first")
    return max(runs, key=lambda p: (p / "config.json").stat().st_mtime)


def load_run(path: str | Path) -> TrainingRun:
    """Read a finished run folder.

    Raises:
        WarpbagsError: a missing or unreadable file, named.
    """
    path = Path(path)
    if not (path / "config.json").is_file():
        raise WarpbagsError(f"{path} is not a training run (no config.json)")
    folder = RunFolder(path)
    info = folder.read_info()
    config = folder.saved_config(info)
    for name in ("gaussians.ply", "poses_true.npy", "poses_init.npy", "poses_final.npy"):
        if not (path / name).is_file():
            raise WarpbagsError(f"{path / name} is missing: the run has not finished (continue it with --resume)")
    poses = {name: torch.from_numpy(folder.read_array(name)) for name in ("poses_true", "poses_init", "poses_final")}
    intrinsics = folder.read_array("intrinsics")
    if intrinsics is not None and len(intrinsics) != len(poses["poses_final"]):
        raise WarpbagsError(f"{path / 'intrinsics.npy'} holds {len(intrinsics)} cameras, the run's poses "
                            f"{len(poses['poses_final'])}")
    return TrainingRun(path, info, config, read_ply(path / "gaussians.ply"), **poses,
                       intrinsics=None if intrinsics is None else torch.from_numpy(intrinsics))
