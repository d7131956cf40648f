"""`RunFolder`: the files of a training run, the one place that writes them; `load_run` reads a finished one.

Layout:
    .starting          while a new run starts (made exclusively, removed once its setup files are written): a
                       second run started into the same folder meanwhile stops instead of writing into it
    config.json        the resolved TrainConfig plus scene/view information (its "normalization": how the scene's
                       world was moved and scaled into the normalized world every file here is in; `warpbags
                       export` writes the Gaussians and poses back in the scene's own)
    poses_true.npy     [C,4,4] world-to-camera poses of the training views
    poses_init.npy     [C,4,4] the (noisy) poses given to training
    poses_start.npy    [C,4,4] the poses the optimization starts from (after the mask-centroid start and the
                       silhouette-coherence solve, where used)
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

from warpbags.cameras import improper_viewmats
from warpbags.configs.train import TrainConfig, is_number, retired_fields
from warpbags.data.scene import Scene, SceneNormalization
from warpbags.errors import WarpbagsError, one_line
from warpbags.files import atomic_output, is_temporary, read_array, temporary_name
from warpbags.gaussians import read_ply, write_ply
from warpbags.pose_history import HISTORY_FILE, RECORD_EVERY, record_poses

CHECKPOINTS_KEPT = 3
# What a checkpoint must hold to be resumed; it also holds "repair" (the repair stage's state, or None).
CHECKPOINT_KEYS = ("iteration", "config", "params", "optimizer", "strategy", "cameras", "generator", "viewmats_init",
                   "viewmats_start")
LOG_FILE = "log.jsonl"
STARTING_FILE = ".starting"
# The fields of every log record that the reports and plots read (the trainer's `_record` writes more).
LOG_NUMBERS = ("loss", "rot_err_deg", "trans_err")
SETUP_FILES = ("config.json", "poses_true.npy", "poses_init.npy", "poses_start.npy", "intrinsics.npy")
RESULT_FILES = ("poses_final.npy", "gaussians.ply")  # `RunFolder.write_results`, in its order
POSE_ARRAYS = ("poses_final", "poses_true", "poses_init", "poses_start")
CAMERA_ARRAYS = (*POSE_ARRAYS, "intrinsics")  # `RunFolder.read_cameras`


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
            WarpbagsError: no config.json, one that cannot be read, or one whose scene and view fields are not of
                the kind `write_setup` writes (a field of an older warpbags that is missing is `require_info`'s).
        """
        path = self.path / "config.json"
        try:
            info = json.loads(_text(path))
        except json.JSONDecodeError as error:
            raise WarpbagsError(f"{path}: unreadable ({error})") from None
        if not isinstance(info, dict):
            raise WarpbagsError(f"{path}: unreadable (not a JSON object)")
        for key, (valid, kind) in _INFO_FIELDS.items():
            if key in info and not valid(info[key]):
                raise WarpbagsError(f"{path}: {key!r} must be {kind}, got {info[key]!r}")
        return info

    def saved_config(self, info: dict | None = None) -> TrainConfig:
        """The TrainConfig in config.json (or in `info`, config.json already read).

        Raises:
            WarpbagsError: no config.json, or one that cannot be read or holds a value of the wrong type or out of
                range (named with the file).
        """
        info = self.read_info() if info is None else info
        if not isinstance(info, dict) or "config" not in info:
            raise WarpbagsError(f"{self.path / 'config.json'} holds no 'config' (not a run's config.json)")
        if not isinstance(info["config"], dict):  # what every reader after this one takes it for
            raise WarpbagsError(f"{self.path / 'config.json'}: 'config' must be a JSON object, got "
                                f"{type(info['config']).__name__}")
        try:
            return TrainConfig.from_dict(info["config"]).validate()
        except (KeyError, TypeError, AttributeError) as error:
            raise WarpbagsError(f"{self.path / 'config.json'}: unreadable ({error})") from None
        except WarpbagsError as error:  # a field of the wrong type ("iters must be like 5000, got 'abc'") or range
            raise WarpbagsError(f"{self.path / 'config.json'}: {error}") from None

    def resumable_config(self, info: dict | None = None) -> TrainConfig:
        """`saved_config`, for a run to be continued: one whose config.json holds settings that this version has no
        more (`RETIRED_FIELDS`) is refused, as it could go on training otherwise than it started (whether a value is
        inert, as camera.restarts=1 was, is not worked out field by field).

        Raises:
            WarpbagsError: as `saved_config`, or such settings, named.
        """
        info = self.read_info() if info is None else info
        saved = info.get("config") if isinstance(info, dict) else None
        retired = retired_fields(saved) if isinstance(saved, dict) else []
        if retired:
            raise WarpbagsError(f"{self.path / 'config.json'} holds {', '.join(retired)}, settings of an earlier "
                                "warpbags that this one has no more: the run cannot be continued (eval, export, "
                                "render and view still read it)")
        return self.saved_config(info)

    def trained_on(self, scene: Scene, info: dict | None = None) -> bool:
        """Whether the run here trained on `scene`'s folder (config.json's, or `info`'s, scene_root)."""
        info = self.read_info() if info is None else info
        return info.get("scene_root") == _root_of(scene)

    def view_differences(self, scene: Scene, info: dict | None = None) -> list[str]:
        """How `scene`'s training views differ from those the run here trained on (config.json's, or `info`'s,
        image_names, width and height): one phrase each, [] when the views and their size are the same."""
        info = self.read_info() if info is None else info
        differences = []
        saved_names = info.get("image_names")
        if saved_names != scene.image_names:
            if not isinstance(saved_names, list):
                differences.append("config.json lists no training views")
            else:
                not_here = [name for name in saved_names if name not in scene.image_names]
                not_saved = [name for name in scene.image_names if name not in saved_names]
                if not_here:
                    differences.append(f"the run's views {_listed(not_here)} are not among the scene's")
                if not_saved:
                    differences.append(f"the scene's views {_listed(not_saved)} are not the run's")
                if not (not_here or not_saved):  # the cameras' order is that of their poses and checkpointed state
                    differences.append("the views are the run's in another order")
        saved_size = (info.get("width"), info.get("height"))
        if saved_size != (scene.width, scene.height):
            differences.append(f"the images are {scene.width}x{scene.height} px, the run's "
                               f"{saved_size[0]}x{saved_size[1]}")
        return differences

    def read_array(self, name: str) -> np.ndarray | None:
        """`name`.npy as float64, checked (`checked_cameras`): [C,4,4] world-to-camera poses (`POSE_ARRAYS`) or
        [C,3,3] intrinsics; None when the run has none. `read_cameras` also checks that they agree on C.

        Raises:
            WarpbagsError: the file exists but cannot be read or is not what its name says, named.
        """
        path = self.path / f"{name}.npy"
        if not path.is_file():
            return None
        array = read_array(path, "camera file").astype(np.float64)
        return checked_cameras(path, array, intrinsics=name == "intrinsics")

    def read_cameras(self, info: dict | None = None) -> dict[str, np.ndarray | None]:
        """Every camera file of the run (`CAMERA_ARRAYS`: the poses and intrinsics.npy) by name, each checked
        (`read_array`; None for a missing one) and all checked to hold the same cameras as each other and as
        config.json's (or `info`'s, config.json already read) image_names: what every reader of a run's cameras
        (`load_run`, the viewer) reads them through.

        Raises:
            WarpbagsError: config.json or a camera file cannot be read, a camera file is malformed, or one of them
                or config.json's image_names holds another number of cameras than poses_final.npy (the first present
                one of `CAMERA_ARRAYS`), named.
        """
        info = self.read_info() if info is None else info
        arrays = {name: self.read_array(name) for name in CAMERA_ARRAYS}
        present = [name for name in CAMERA_ARRAYS if arrays[name] is not None]
        for name in present[1:]:
            if len(arrays[name]) != len(arrays[present[0]]):
                raise WarpbagsError(f"{self.path / f'{name}.npy'} holds {len(arrays[name])} cameras, the run's poses "
                                    f"{len(arrays[present[0]])} ({present[0]}.npy)")
        # the views' names go with the cameras by position (the viewer's pictures, export's COLMAP model, eval's
        # held-out split): a list of another length crashed the viewer where its pictures ran out (an IndexError) and
        # exported a model of as many cameras as it names
        names = info.get("image_names")
        if present and names is not None and len(names) != len(arrays[present[0]]):
            raise WarpbagsError(f"{self.path / 'config.json'}: 'image_names' lists {len(names)} training views, the "
                                f"run's poses {len(arrays[present[0]])} ({present[0]}.npy)")
        return arrays

    def write_results(self, params: dict[str, torch.Tensor], viewmats: torch.Tensor) -> None:
        """poses_final.npy ([C,4,4] world-to-camera), then gaussians.ply: last, as `latest_run` takes a run holding it
        for a finished one (written first, a failure before the poses left eval and export a run they refused)."""
        with atomic_output(self.path / "poses_final.npy") as temporary:
            np.save(temporary, viewmats.cpu().numpy())
        write_ply(self.path / "gaussians.ply", params)

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
        """The per-iteration records of log.jsonl ([] without one).

        Raises:
            WarpbagsError: the file cannot be read, or a line is not a record (a line cut short by a crash, or
                without an iteration count or one of `LOG_NUMBERS`), named with its line number.
        """
        path = self.path / LOG_FILE
        if not path.is_file():
            return []
        records = []
        for number, line in enumerate(_text(path).splitlines(), start=1):
            if not line.strip():
                continue
            try:
                record = json.loads(line)
            except json.JSONDecodeError as error:
                raise WarpbagsError(f"{path}:{number}: not a log record ({error.msg}; cut short by a crash?)") from None
            if not isinstance(record, dict) or not _is_count(record.get("iter")):
                raise WarpbagsError(f"{path}:{number}: not a log record (no iteration count \"iter\")")
            missing = [name for name in LOG_NUMBERS if not is_number(record.get(name))]
            if missing:
                raise WarpbagsError(f"{path}:{number}: not a log record (no number \"{missing[0]}\")")
            records.append(record)
        return records

    def record_poses(self, iteration: int, viewmats: torch.Tensor) -> None:
        """Append [C,4,4] `viewmats` to the pose history when `iteration` is a multiple of RECORD_EVERY."""
        if iteration % RECORD_EVERY == 0:
            record_poses(self.path, iteration, viewmats)

    def truncate(self, iteration: int, viewmats: torch.Tensor) -> None:
        """Drop what was logged after `iteration` (a resumed run replays those iterations): log.jsonl lines (and a
        line cut short by a crash) and pose-history records; the history then ends with [C,4,4] `viewmats`, the
        poses at `iteration`.

        Raises:
            WarpbagsError: log.jsonl cannot be read (not text), named.
        """
        path = self.path / LOG_FILE
        if path.exists():
            kept = []
            for line in _text(path).splitlines():
                try:
                    if json.loads(line)["iter"] <= iteration:
                        kept.append(line)
                except (json.JSONDecodeError, KeyError, TypeError):
                    continue
            with atomic_output(path) as temporary:
                temporary.write_text("".join(line + "\n" for line in kept))
        if (self.path / HISTORY_FILE).exists():
            record_poses(self.path, iteration, viewmats)  # records at or after `iteration` are replaced

    # ----------------------------------------------------------------------------------------------- a new run
    def require_new(self) -> None:
        """Check that a new run may start here: the folder is missing or empty, so that it overwrites nothing and
        appends to no other run's log (and a failed start can remove what it wrote, `remove_unfinished`).

        Raises:
            WarpbagsError: the folder holds anything; a run with a checkpoint is named as one (--resume continues it).
        """
        if not self.path.is_dir():
            return
        entries = sorted(entry.name for entry in self.path.iterdir())
        if not entries:
            return
        if STARTING_FILE in entries and not self.has_checkpoint():
            raise WarpbagsError(self._starting_message())
        if self.has_checkpoint():
            raise WarpbagsError(f"{self.path} already holds a run; pass --resume to continue it or choose another "
                                "--out")
        if self.holds_unfinished_start():
            raise WarpbagsError(f"{self.path} holds a run stopped before its first checkpoint (nothing to --resume): "
                                "remove the folder or choose another --out")
        shown = ", ".join(entries[:6]) + (f" and {len(entries) - 6} more" if len(entries) > 6 else "")
        raise WarpbagsError(f"{self.path} is not empty ({shown}) and holds no run to --resume: a new run needs a new "
                            "or empty folder, choose another --out")

    def claim_new(self) -> None:
        """Make the folder (with its parents) and claim it for a new run by creating STARTING_FILE exclusively:
        of two runs started into one folder, which both found it empty (`require_new`), the second stops here.

        Raises:
            WarpbagsError: another run holds the claim.
        """
        self.path.mkdir(parents=True, exist_ok=True)
        try:
            (self.path / STARTING_FILE).open("x").close()
        except FileExistsError:
            raise WarpbagsError(self._starting_message()) from None

    def release_claim(self) -> None:
        """Remove the claim of `claim_new` (the run's setup files now tell the folder is taken)."""
        (self.path / STARTING_FILE).unlink(missing_ok=True)

    def _starting_message(self) -> str:
        return (f"another run is starting in {self.path} (or one was killed while it started: then remove the "
                "folder); choose another --out")

    def holds_unfinished_start(self) -> bool:
        """Whether the folder holds nothing but what a new run writes before its first checkpoint (its setup files,
        log and pose history, their atomic writes' temporaries, a checkpoints/ that is empty or holds only the
        temporary of a checkpoint write cut short, a coarse/ of the coarse stage's setup files and results, which a
        repair stage writes before its first checkpoint where --checkpoint-every is above --iters): a run killed there
        (SIGKILL, power), which can be neither resumed nor evaluated, and which `remove_unfinished` may clear."""
        if not self.path.is_dir() or self.has_checkpoint():
            return False
        names = {*SETUP_FILES, LOG_FILE, HISTORY_FILE}
        names |= {temporary_name(name) for name in names} | {STARTING_FILE}
        coarse_names = {*SETUP_FILES, *RESULT_FILES}
        coarse_names |= {temporary_name(name) for name in coarse_names}

        def written(entry: Path, written_names: set[str]) -> bool:
            return entry.name in written_names and entry.is_file() and not entry.is_symlink()

        entries = list(self.path.iterdir())
        return bool(entries) and all(
            written(entry, names)
            or (entry == self.checkpoints and entry.is_dir()
                and set(entry.iterdir()) <= set(self._cut_short_checkpoints()))
            or (entry == self.path / "coarse" and entry.is_dir() and not entry.is_symlink()
                and all(written(file, coarse_names) for file in entry.iterdir()))
            for entry in entries)

    def remove_unfinished(self, made_folders: list[Path]) -> None:
        """Remove what a new run writes before its first checkpoint (its setup files, log, pose history, an
        unfinished coarse/, and checkpoints/ with the temporary of a checkpoint write cut short), then those of
        `made_folders` (`files.missing_folders` before the run started) that are empty. Only for a run that started
        in a new or empty folder (`require_new`) and has no checkpoint: it cannot be resumed, and a half-written run
        folder must not stay."""
        for folder in (self.path / "coarse", self.path):
            for name in (*SETUP_FILES, *RESULT_FILES, LOG_FILE, HISTORY_FILE):
                for written in (name, temporary_name(name)):  # and a write cut short
                    (folder / written).unlink(missing_ok=True)
        for cut_short in self._cut_short_checkpoints():
            cut_short.unlink()
        self.release_claim()
        for folder in (self.path / "coarse", self.checkpoints, *made_folders):
            try:
                folder.rmdir()
            except OSError:  # missing, or not empty: left as it is
                pass

    # ----------------------------------------------------------------------------------------------- checkpoints
    def has_checkpoint(self) -> bool:
        return self.latest_checkpoint() is not None

    def latest_checkpoint(self) -> Path | None:
        found = self._checkpoints()
        return found[-1] if found else None

    def _checkpoints(self) -> list[Path]:
        """The checkpoints written in full, oldest first: by iteration, not by name (checkpoint_1000000 sorts before
        checkpoint_999999 as text)."""
        found = [path for path in self.checkpoints.glob("checkpoint_*.pt")
                 if not is_temporary(path) and _iteration_of(path) is not None]  # not another file named alike
        return sorted(found, key=_iteration_of)

    def _cut_short_checkpoints(self) -> list[Path]:
        """The temporaries of checkpoint writes cut short by a kill (checkpoint_N.tmp.pt, `atomic_output`)."""
        return [path for path in self.checkpoints.glob("checkpoint_*.pt") if is_temporary(path) and path.is_file()
                and not path.is_symlink()]

    def save_checkpoint(self, state: dict) -> Path:
        """Write `state` (the keys of CHECKPOINT_KEYS and "repair") atomically as checkpoint_<iteration>.pt; keep
        the newest CHECKPOINTS_KEPT, and remove the temporaries of earlier writes cut short."""
        missing = [key for key in CHECKPOINT_KEYS if key not in state]
        if missing:
            raise ValueError(f"checkpoint state lacks {missing}")
        self.checkpoints.mkdir(parents=True, exist_ok=True)
        path = self.checkpoints / f"checkpoint_{state['iteration']:06d}.pt"
        try:
            with atomic_output(path) as temporary:
                torch.save(state, temporary)
        except RuntimeError as error:  # torch's writer says a failed write so ("unexpected pos", a full disk)
            raise OSError(f"torch.save failed ({' '.join(str(error).split())})") from error
        for old in (*self._checkpoints()[:-CHECKPOINTS_KEPT], *self._cut_short_checkpoints()):
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


def checked_cameras(path: Path, array: np.ndarray, intrinsics: bool = False) -> np.ndarray:
    """`array`, read from `path`, checked to be [C,4,4] world-to-camera poses (finite, a rotation and a translation
    over the row [0, 0, 0, 1]: `cameras.improper_viewmats`) or, with `intrinsics`, [C,3,3] finite intrinsics with
    focal lengths above 0, C >= 1.

    Raises:
        WarpbagsError: it is not, naming `path` and the first camera that is not.
    """
    side, what = (3, "intrinsics") if intrinsics else (4, "world-to-camera poses")
    if array.ndim != 3 or array.shape[1:] != (side, side) or len(array) == 0:
        raise WarpbagsError(f"{path}: expected [C,{side},{side}] {what}, got an array of shape {list(array.shape)}")
    finite = np.isfinite(array).all(axis=(1, 2))
    if not finite.all():
        raise WarpbagsError(f"{path}: camera {int(np.argmin(finite))} holds a value that is not finite")
    if intrinsics:
        unfocused = np.flatnonzero((array[:, 0, 0] <= 0) | (array[:, 1, 1] <= 0))
        if len(unfocused):
            camera = int(unfocused[0])
            raise WarpbagsError(f"{path}: camera {camera} has focal lengths {array[camera, 0, 0]:g} and "
                                f"{array[camera, 1, 1]:g} px, not both above 0")
    improper = [] if intrinsics else improper_viewmats(torch.from_numpy(array)).tolist()
    if improper:
        camera = improper[0]
        raise WarpbagsError(f"{path}: camera {camera} is not a world-to-camera pose (its 3x3 part has determinant "
                            f"{np.linalg.det(array[camera, :3, :3]):.3g}, last row {array[camera, 3].tolist()})")
    return array


# config.json's scene and view fields (`RunFolder.write_setup`): a check of each and what it says is expected
_INFO_FIELDS = {
    "scene": (lambda value: isinstance(value, str), "a scene name (text)"),
    "scene_root": (lambda value: isinstance(value, str) and bool(value), "a folder (text)"),
    "resolution": (lambda value: type(value) is int and value in (1, 2, 4, 8), "1, 2, 4 or 8"),
    "image_names": (lambda value: isinstance(value, list) and all(isinstance(name, str) for name in value),
                    "a list of image names"),
    "width": (lambda value: type(value) is int and value > 0, "a positive whole number of pixels"),
    "height": (lambda value: type(value) is int and value > 0, "a positive whole number of pixels"),
    "normalization": (lambda value: isinstance(value, dict), "an object (the scene's normalization)"),
    "device": (lambda value: isinstance(value, str), "a device name (text)"),
}


def _text(path: Path) -> str:
    """The text of the run file `path`.

    Raises:
        WarpbagsError: it cannot be read, or is not text, named.
    """
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise WarpbagsError(f"{path}: unreadable ({error})") from None


def _is_count(value) -> bool:
    return is_number(value) and isinstance(value, int) and value >= 0


def _listed(names: list[str]) -> str:
    """The first names of `names` and how many more, for a one-line message."""
    return ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")


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


def run_normalization(run: TrainingRun) -> SceneNormalization:
    """The run's scene normalization, as its config.json stores it.

    Raises:
        WarpbagsError: config.json has none (an older warpbags) or a malformed one, named.
    """
    require_info(run, "normalization")
    try:
        return SceneNormalization.from_dict(run.info["normalization"])
    except WarpbagsError as error:
        raise WarpbagsError(f"{run.path / 'config.json'}: {error}") from None


def latest_run(root: str | Path = "runs") -> Path:
    """The run folder under `root` that finished last (by its gaussians.ply, written with the result): a run still
    training, started later, is passed over (eval, export and render, which ask for this, read finished runs).

    Raises:
        WarpbagsError: no finished run there.
    """
    runs = [p.parent for p in Path(root).glob("*/config.json")]
    finished = [run for run in runs if (run / "gaussians.ply").is_file()]
    if not finished:
        unfinished = f" ({len(runs)} unfinished)" if runs else ""
        raise WarpbagsError(f"no finished training run under {Path(root).resolve()}{unfinished}; pass RUN_DIR or "
                            "train first")
    return max(finished, key=lambda run: (run / "gaussians.ply").stat().st_mtime)


def load_run(path: str | Path) -> TrainingRun:
    """Read a finished run folder.

    Raises:
        WarpbagsError: a missing, unreadable or malformed file (`RunFolder.read_cameras`, `read_ply`), named.
    """
    path = Path(path)
    if path.is_file():
        raise WarpbagsError(f"{path} is a file: name the run's folder")
    if not path.exists():
        raise WarpbagsError(f"{path}: no such run folder")
    if not (path / "config.json").is_file():
        raise WarpbagsError(f"{path} is not a training run (no config.json)")
    folder = RunFolder(path)
    info = folder.read_info()
    config = folder.saved_config(info)
    if not (path / "gaussians.ply").is_file():
        if not folder.has_checkpoint():  # killed before it (SIGKILL, power): --resume has nothing to continue
            raise WarpbagsError(f"{path / 'gaussians.ply'} is missing: the run stopped before its first checkpoint, "
                                "so it cannot be resumed; train it again into an empty folder")
        raise WarpbagsError(f"{path / 'gaussians.ply'} is missing: the run has not finished (continue it with "
                            "--resume)")
    for name in ("poses_true.npy", "poses_init.npy", "poses_final.npy"):  # written at the start and with the result
        if not (path / name).is_file():
            raise WarpbagsError(f"{path / name} is missing from the finished run")
    arrays = folder.read_cameras(info)  # all checked, poses_start.npy too: [C,4,4] poses, [C,3,3] intrinsics, C views
    poses = {name: torch.from_numpy(arrays[name]) for name in ("poses_true", "poses_init", "poses_final")}
    intrinsics = arrays["intrinsics"]
    return TrainingRun(path, info, config, read_ply(path / "gaussians.ply"), **poses,
                       intrinsics=None if intrinsics is None else torch.from_numpy(intrinsics))


def _iteration_of(checkpoint: Path) -> int | None:
    """The iteration in a checkpoint's name (checkpoint_000500.pt), None for a name that holds none."""
    digits = checkpoint.stem.removeprefix("checkpoint_")
    return int(digits) if digits.isascii() and digits.isdigit() else None
