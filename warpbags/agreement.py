"""How far several runs of one capture agree on its camera poses: a sign of whether the views determine them that
needs no reference poses.

Runs that start from the same given poses and differ only in their training seed (the Gaussians' initial sample,
and so every step after it) end where the images let them: on a capture whose views pin the cameras they end close
together, on one whose views do not they end apart. The measured relation (README, "Pose recovery"): on the
telephoto synthetic scene three such runs disagree by 0.50 deg (mean over camera pairs of runs) and end 0.56 deg
from the truth; on maryrose with four views they disagree by 4.5 deg and end 9.1 deg from its reference poses. The
disagreement is a lower bound of the error, not an estimate of it: what all runs share (the start, the views'
own ambiguity) is not seen.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from warpbags.alignment import alignment_for, pose_errors, reprojection_errors
from warpbags.data import ORBIT_RADIUS
from warpbags.errors import WarpbagsError
from warpbags.gaussians import object_points
from warpbags.run_folder import TrainingRun, require_info


@dataclass(frozen=True)
class PoseAgreement:
    """The final poses of several runs compared pair by pair, camera by camera.

    Attributes:
        runs: the run folders, in the order given.
        image_names: the training views, the cameras' order.
        alignment: how each pair was aligned ("procrustes" from 3 cameras, else "pairwise").
        pairs: (i, j) indices into `runs`, i < j.
        rotation_deg: [P, C] angle between the two runs' orientations of each camera, after a sim(3) alignment of
            run i's cameras to run j's.
        centre_percent: [P, C] distance between the aligned camera centres, % of the orbit radius.
        pixels: [P, C] RMS pixels (training resolution) between where the two runs' cameras put run i's object;
            None where a run saved no intrinsics (an older warpbags).
    """

    runs: list[Path]
    image_names: list[str]
    alignment: str
    pairs: list[tuple[int, int]]
    rotation_deg: np.ndarray
    centre_percent: np.ndarray
    pixels: np.ndarray | None

    def run_disagreement_deg(self) -> np.ndarray:
        """[R] each run's mean rotation disagreement with the others (over its pairs and the cameras)."""
        totals = np.zeros(len(self.runs))
        for (i, j), angles in zip(self.pairs, self.rotation_deg):
            totals[i] += angles.mean()
            totals[j] += angles.mean()
        return totals / (len(self.runs) - 1)

    def central_run(self) -> int:
        """The index of the run that disagrees least with the others: the one to keep if one is to be kept."""
        return int(np.argmin(self.run_disagreement_deg()))

    def to_json(self) -> dict:
        per_camera = {
            "rotation_deg_median": np.median(self.rotation_deg, axis=0).tolist(),
            "rotation_deg_max": self.rotation_deg.max(axis=0).tolist(),
            "centre_percent_of_orbit_max": self.centre_percent.max(axis=0).tolist(),
        }
        if self.pixels is not None:
            per_camera["pixels_max"] = self.pixels.max(axis=0).tolist()
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
            "central_run": str(self.runs[self.central_run()]),
        }


def pose_agreement(runs: Sequence[TrainingRun], preferred: str = "procrustes") -> PoseAgreement:
    """Compare the final poses of `runs`, every pair of them.

    Raises:
        WarpbagsError: fewer than two runs, or a run of another scene folder or other training views than the
            first, named.
    """
    if len(runs) < 2:
        raise WarpbagsError(f"agreement needs at least two runs of one capture, got {len(runs)}")
    for run in runs:
        require_info(run, "scene_root", "image_names")
    first = runs[0]
    for run in runs[1:]:
        if run.info["scene_root"] != first.info["scene_root"]:
            raise WarpbagsError(f"{run.path} is a run of {run.info['scene_root']}, {first.path} of "
                                f"{first.info['scene_root']}: compare runs of one capture")
        if run.info["image_names"] != first.info["image_names"]:
            raise WarpbagsError(f"{run.path} was trained on other views than {first.path} "
                                f"({', '.join(run.info['image_names'])}): compare runs of the same views")
    alignment = alignment_for(len(first.info["image_names"]), preferred)
    pairs = list(itertools.combinations(range(len(runs)), 2))
    rotations, centres, pixels = [], [], []
    for i, j in pairs:
        try:
            errors = pose_errors(runs[i].poses_final.double(), runs[j].poses_final.double(), alignment=alignment)
        except ValueError as error:  # cameras in a line, or a run whose poses collapsed
            raise WarpbagsError(f"{runs[i].path} against {runs[j].path}: {error}") from None
        rotations.append(errors["rotation_errors_deg"].numpy())
        centres.append(100 * errors["translation_errors"].numpy() / ORBIT_RADIUS)
        if runs[j].intrinsics is not None:
            points = errors["sim3"].apply(object_points(runs[i].params).double())  # run i's object in run j's frame
            pixels.append(reprojection_errors(runs[i].poses_final.double(), runs[j].poses_final.double(),
                                              runs[j].intrinsics.double(), points, errors["sim3"]).numpy())
    return PoseAgreement(runs=[run.path for run in runs], image_names=list(first.info["image_names"]),
                         alignment=alignment, pairs=pairs, rotation_deg=np.stack(rotations),
                         centre_percent=np.stack(centres),
                         pixels=np.stack(pixels) if len(pixels) == len(pairs) else None)
