"""How far several runs of one capture agree on its camera poses: a sign of whether the views determine them that
needs no reference poses.

Runs that start from the same given poses and differ only in their training seed (the Gaussians' initial sample,
and so every step after it) end where the images let them: on a capture whose views pin the cameras they end close
together, on one whose views do not they end apart. Two runs d degrees apart on a camera cannot both be within
d / 2 of its true pose (up to the alignments), so the disagreement bounds the error from below; what all runs share
(the start, the views' own ambiguity) it does not see. Measured relation: README, "Pose recovery".
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from warpbags.alignment import alignment_for, pose_errors, reprojection_errors
from warpbags.cameras import camera_centers
from warpbags.errors import WarpbagsError
from warpbags.gaussians import object_points
from warpbags.run_folder import TrainingRun, require_info


@dataclass(frozen=True)
class PoseAgreement:
    """The final poses of several runs compared pair by pair, camera by camera.

    Attributes:
        runs: the run folders, in the order given.
        image_names: the training views, the cameras' order.
        alignment: how each pair was aligned: the one asked for, "pairwise" where Procrustes cannot be fitted
            (fewer than 3 cameras).
        pairs: (i, j) indices into `runs`, i < j.
        rotation_deg: [P, C] angle between the two runs' orientations of each camera, after a sim(3) alignment of
            run i's cameras to run j's.
        centre_percent: [P, C] distance between the aligned camera centres, % of run j's orbit radius (its cameras'
            mean distance from its object, in its own frame).
        pixels: [P, C] RMS pixels (training resolution) between where the two runs' cameras put run i's object;
            None when a run saved no intrinsics (an older warpbags).
        same_start: whether every run started from the same poses (`poses_init`); if not, the disagreement
            includes how far apart they started.
        error_deg: [R, C] each run's rotation error against the scene's poses, with the same alignment, when every
            run perturbed them before training (an experiment: they are the truth); else None.
    """

    runs: list[Path]
    image_names: list[str]
    alignment: str
    pairs: list[tuple[int, int]]
    rotation_deg: np.ndarray
    centre_percent: np.ndarray
    pixels: np.ndarray | None
    same_start: bool
    error_deg: np.ndarray | None

    def run_disagreement_deg(self) -> np.ndarray:
        """[R] each run's mean rotation disagreement with the others (over its pairs and the cameras)."""
        totals = np.zeros(len(self.runs))
        for (i, j), angles in zip(self.pairs, self.rotation_deg):
            totals[i] += angles.mean()
            totals[j] += angles.mean()
        return totals / (len(self.runs) - 1)

    def central_run(self) -> int | None:
        """The index of the run that disagrees least with the others: the one to keep if one is to be kept; None
        where no one run does (two runs are always level with each other, and a tie names none)."""
        disagreements = self.run_disagreement_deg()
        least = np.flatnonzero(disagreements == disagreements.min())
        return int(least[0]) if len(self.runs) > 2 and len(least) == 1 else None

    def per_camera(self) -> dict[str, np.ndarray]:
        """[C] summaries over the pairs: the median and largest rotation disagreement, the largest centre distance
        (% of the orbit) and, where the runs saved intrinsics, the largest pixel distance."""
        summary = {
            "rotation_deg_median": np.median(self.rotation_deg, axis=0),
            "rotation_deg_max": self.rotation_deg.max(axis=0),
            "centre_percent_of_orbit_max": self.centre_percent.max(axis=0),
        }
        if self.pixels is not None:
            summary["pixels_max"] = self.pixels.max(axis=0)
        return summary

    def to_json(self) -> dict:
        per_camera = {name: values.tolist() for name, values in self.per_camera().items()}
        return {
            "runs": [str(path) for path in self.runs],
            "image_names": self.image_names,
            "alignment": self.alignment,
            "pairs": [list(pair) for pair in self.pairs],
            "rotation_deg": self.rotation_deg.tolist(),
            "centre_percent_of_orbit": self.centre_percent.tolist(),
            "pixels": None if self.pixels is None else self.pixels.tolist(),
            "per_camera": per_camera,
            "rotation_deg_mean": float(self.rotation_deg.mean()),
            "run_disagreement_deg": self.run_disagreement_deg().tolist(),
            "central_run": None if self.central_run() is None else str(self.runs[self.central_run()]),
            "same_start": self.same_start,
            "error_deg": None if self.error_deg is None else self.error_deg.tolist(),
        }


def pose_agreement(runs: Sequence[TrainingRun], preferred: str = "procrustes") -> PoseAgreement:
    """Compare the final poses of `runs`, every pair of them.

    Raises:
        WarpbagsError: fewer than two runs; a run given twice; a run of another scene folder, other training views
            or another training resolution than the first, or with poses that are not finite, named.
    """
    if len(runs) < 2:
        raise WarpbagsError(f"agreement needs at least two runs of one capture, got {len(runs)}")
    for run in runs:
        require_info(run, "scene_root", "image_names", "width", "height")
        if not torch.isfinite(run.poses_final).all():
            raise WarpbagsError(f"{run.path / 'poses_final.npy'} holds poses that are not finite")
    first, seen = runs[0], set()
    for run in runs:  # a run compared with itself agrees to the bit and says nothing
        if Path(run.path).resolve() in seen:
            raise WarpbagsError(f"{run.path} is given twice: compare different runs of one capture")
        seen.add(Path(run.path).resolve())
    for run in runs[1:]:
        if run.info["scene_root"] != first.info["scene_root"]:
            raise WarpbagsError(f"{run.path} is a run of {run.info['scene_root']}, {first.path} of "
                                f"{first.info['scene_root']}: compare runs of one capture")
        if run.info["image_names"] != first.info["image_names"]:
            raise WarpbagsError(f"{run.path} was trained on other views than {first.path} "
                                f"({', '.join(run.info['image_names'])}): compare runs of the same views")
        if (run.info["width"], run.info["height"]) != (first.info["width"], first.info["height"]):
            raise WarpbagsError(f"{run.path} trained at {run.info['width']}x{run.info['height']} px, {first.path} at "
                                f"{first.info['width']}x{first.info['height']}: compare runs of one resolution")
    alignment = alignment_for(first.poses_true, preferred)  # the views are the same, and so are their references
    pairs = list(itertools.combinations(range(len(runs)), 2))
    with_intrinsics = all(run.intrinsics is not None for run in runs)
    rotations, centres, pixels = [], [], []
    orbit_radii = [_orbit_radius(run) for run in runs]
    for i, j in pairs:
        errors = _errors(runs[i].poses_final, runs[j].poses_final, alignment, f"{runs[i].path} against {runs[j].path}")
        rotations.append(errors["rotation_errors_deg"].numpy())
        centres.append(100 * errors["translation_errors"].numpy() / orbit_radii[j])
        if with_intrinsics:
            points = errors["sim3"].apply(object_points(runs[i].params).double())  # run i's object in run j's frame
            pixels.append(reprojection_errors(runs[i].poses_final.double(), runs[j].poses_final.double(),
                                              runs[j].intrinsics.double(), points, errors["sim3"]).numpy())
    noisy = all(run.config.injects_pose_noise for run in runs)
    error_deg = (np.stack([_errors(run.poses_final, run.poses_true, alignment, str(run.path))["rotation_errors_deg"]
                           .numpy() for run in runs]) if noisy else None)
    same_start = all(torch.allclose(run.poses_init.double(), first.poses_init.double(), atol=1e-6) for run in runs)
    return PoseAgreement(runs=[run.path for run in runs], image_names=list(first.info["image_names"]),
                         alignment=alignment, pairs=pairs, rotation_deg=np.stack(rotations),
                         centre_percent=np.stack(centres), pixels=np.stack(pixels) if with_intrinsics else None,
                         same_start=same_start, error_deg=error_deg)


def _orbit_radius(run: TrainingRun) -> float:
    """The mean distance of `run`'s cameras from its object (its opaque Gaussians' mean) in its own frame: the
    normalized scene's 4 scaled as training left the frame (about 6% larger on the telephoto synthetic scene)."""
    centre = object_points(run.params).double().mean(0)
    return float((camera_centers(run.poses_final.double()) - centre).norm(dim=-1).mean())


def _errors(viewmats: torch.Tensor, viewmats_ref: torch.Tensor, alignment: str, what: str) -> dict:
    """`pose_errors` in float64, its failure (cameras in a line, poses collapsed to a point) as one line."""
    try:
        return pose_errors(viewmats.double(), viewmats_ref.double(), alignment=alignment)
    except ValueError as error:
        raise WarpbagsError(f"{what}: {error}") from None
