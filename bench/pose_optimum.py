"""Where the photometric optimum sits: Gaussians fitted at the reference poses (frozen), then the poses alone.

    python bench/pose_optimum.py SCENE [SCENE ...] [--views 4] [--fit-iters 50,200,400] [--pose-iters 100]
        [--max-image-size 128] [--pose-lr 3e-3] [--optimizer adam|lbfgs] [--start-noise 0/0,5/0.1] [--preset quick]
        [--set NAME=VALUE ...] [--json PATH]

SCENE: as bench/pose_recovery.py (a preset, a folder, `synthetic-small` or `synthetic-tele-small`). For each
scene, one model is trained on the training views at their reference poses, frozen (no noise, no mask-centroid
start; one round of the preset's schedule otherwise). After `fit` iterations of it, for each value of
--fit-iters, a copy of the camera optimizer takes --pose-iters Adam steps (or L-BFGS iterations, as test-pose
refinement does: `--optimizer lbfgs`) with every training view rendered and the Gaussians held fixed; the poses it reaches are compared with the reference after sim(3) Procrustes alignment
(mean and max rotation error, centre floor, camera centres in % of the orbit radius), then the model trains on.
With --start-noise ROT/TRANS[,...] the pose-only steps start, once per pair, from the reference poses perturbed as
`--rot-noise-deg ROT --trans-noise TRANS` would (noise seed 0) instead of from the reference: how wide the basin
of a model that fits the reference is.

This separates the two things a joint optimization mixes: how far a model's own pose optimum sits from the
reference (the bias of a half-fitted model, the resolution, the data) and how far the joint optimization
wanders from it when the Gaussians follow the poses (bench/pose_recovery.py's truth-start variant).

`--set` takes any TrainConfig field but those this setup fixes (`FIXED`: views, the noise, rounds, iters, pose_opt,
pose_opt_start, repair.iters, camera.centroid_start and camera.coherence_iters), a one-line error.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import math
import tempfile
import time

import numpy as np
import torch

from common import (add_training_options, check_json, check_options, check_view_counts, merge_settings,
                    open_bench_scene, procrustes_views_check, training_overrides, write_json)
from warpbags.alignment import centre_floor_errors, pose_errors
from warpbags.configs.train import load_preset
from warpbags.data import ORBIT_RADIUS
from warpbags.data.noise import perturb_viewmats
from warpbags.errors import WarpbagsError
from warpbags.trainer import Trainer, training_scene
from warpbags.cli.common import clean_errors, parse_numbers

# The fields this benchmark sets itself (`run_settings`), and where each value comes from.
FIXED = {"views": "from --views", "rot_noise_deg": "0: the fits start at the reference, see --start-noise",
         "trans_noise": "0: the fits start at the reference, see --start-noise", "rounds": "1",
         "iters": "from --fit-iters", "pose_opt": "on, for the pose-only steps",
         "pose_opt_start": "never: the fits keep the poses frozen", "repair.iters": "0: no repair stage",
         "camera.centroid_start": "off: the fits start at the reference",
         "camera.coherence_iters": "0: the fits start at the reference"}


def _errors(trainer: Trainer, viewmats: torch.Tensor) -> dict:
    estimate, reference = viewmats.double().cpu(), trainer.viewmats_true.double().cpu()
    errors = pose_errors(estimate, reference, alignment="procrustes")
    rotations = np.asarray(errors["rotation_errors_deg"], dtype=float)
    floor = centre_floor_errors(estimate, reference, torch.zeros(3, dtype=torch.float64))
    return {"rotation_mean": float(rotations.mean()), "rotation_max": float(rotations.max()),
            "centre_floor": float(np.mean(np.asarray(floor, dtype=float))),
            "translation_pct": 100 * float(errors["translation_error_mean"]) / ORBIT_RADIUS}


def pose_only_optimum(trainer: Trainer, steps: int, lr: float, start_noise: tuple[float, float] = (0.0, 0.0),
                      optimizer: str = "adam") -> dict:
    """Adam steps (or L-BFGS iterations, `CameraOptimizer.refine`) of a copy of the trainer's cameras, started from
    the reference poses perturbed by `start_noise` (rotation std in degrees, centre std in scene units), against its
    current Gaussians (held fixed); the errors at the start and at the end. The trainer's own cameras and Gaussians
    are left as they were."""
    cameras = copy.deepcopy(trainer.cameras)
    with torch.no_grad():
        cameras.base_viewmats.copy_(perturb_viewmats(trainer.viewmats_true.to(cameras.base_viewmats), *start_noise,
                                                     seed=0))
    start = _errors(trainer, cameras.viewmats())
    cameras.reset_moments()
    cameras.set_learning_rate(lr)
    model, views = trainer.model, torch.arange(trainer.num_cameras)
    settings = dataclasses.replace(trainer.schedule.at(trainer.iteration), pose_active=True, depth=False)
    if optimizer == "lbfgs":
        cameras.refine(lambda viewmats: model.loss(views, viewmats, settings)[0], steps)
    else:
        for _ in range(steps):
            loss, _, _ = model.loss(views, cameras(views), settings)
            loss.backward()
            cameras.step(views)
            cameras.zero_grad()
    model.optimizer.zero_grad(set_to_none=True)
    return {"start_rotation_mean": start["rotation_mean"], **_errors(trainer, cameras.viewmats())}


def run_settings(views: int, fit_iters: list[int], overrides: dict) -> dict:
    """The `load_preset` settings of a scene's model: the reference poses frozen (no noise, no mask-centroid start,
    no coherence solve), one round long enough for every --fit-iters value, `overrides` (`--set`) on top."""
    settings = dict(views=views, rot_noise_deg=0.0, trans_noise=0.0, rounds=1, iters=max(fit_iters) + 1,
                    pose_opt=True, pose_opt_start=10**9, repair={"iters": 0},
                    camera={"centroid_start": False, "coherence_iters": 0})
    return merge_settings(settings, overrides)


def parse_start_noise(text: str) -> list[tuple[float, float]]:
    """--start-noise: comma-separated ROT_DEG/TRANS pairs, e.g. "0/0,5/0.1".

    Raises:
        WarpbagsError: an item that is not two numbers joined by "/", or no pair at all.
    """
    pairs = []
    for item in text.split(","):
        if not item.strip():
            continue
        try:
            rot, trans = (float(value) for value in item.split("/"))
        except ValueError:
            raise WarpbagsError(f"--start-noise {text!r}: {item.strip()!r} is not ROT_DEG/TRANS "
                                "(comma-separated pairs such as 0/0,5/0.1)") from None
        pairs.append((rot, trans))
    if not pairs:
        raise WarpbagsError(f"--start-noise {text!r}: expected comma-separated ROT_DEG/TRANS pairs, got none")
    return pairs


def run_scene(name: str, scene, views: int, fit_iters: list[int], pose_iters: int, lr: float, preset: str,
              overrides: dict, start_noises: list[tuple[float, float]], optimizer: str = "adam") -> list[dict]:
    config = load_preset(preset, **run_settings(views, fit_iters, overrides))
    with tempfile.TemporaryDirectory(prefix="pose-optimum-") as folder:  # removed after, as nothing there is kept
        trainer = Trainer(training_scene(scene, config), config, folder, log=lambda message: None)
        rows, started = [], time.time()
        for fit in sorted(fit_iters):
            while trainer.iteration < fit:
                trainer.train_step()
            for noise in start_noises:
                row = {"scene": name, "views": views, "size": trainer.scene.width, "fit_iters": fit,
                       "optimizer": optimizer, "pose_iters": pose_iters, "start_noise": list(noise),
                       **pose_only_optimum(trainer, pose_iters, lr, noise, optimizer),
                       "minutes": (time.time() - started) / 60}
                rows.append(row)
                print(f"{name:<22} {views:>5} {row['size']:>5} {fit:>8} {noise[0]:>5g}/{noise[1]:<5g}"
                      f" {row['start_rotation_mean']:>9.2f} {row['rotation_mean']:>10.2f} {row['rotation_max']:>8.2f}"
                      f" {row['centre_floor']:>12.2f} {row['translation_pct']:>14.2f} {row['minutes']:>8.1f}", flush=True)
        return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--fit-iters", default="50,200,400", help="comma-separated iterations of Gaussian fitting")
    parser.add_argument("--pose-iters", type=int, default=100)
    parser.add_argument("--pose-lr", type=float, default=3e-3, help="the rotation lr of the pose-only Adam steps")
    parser.add_argument("--optimizer", choices=("adam", "lbfgs"), default="adam",
                        help="pose-only steps: Adam (as training) or L-BFGS (as test-pose refinement); with lbfgs, "
                             "--pose-iters counts its iterations")
    parser.add_argument("--start-noise", default="0/0", help="comma-separated ROT_DEG/TRANS pairs")
    parser.add_argument("--max-image-size", type=int, default=None, help="default: the preset's")
    add_training_options(parser, "a TrainConfig field for every model (repeatable), as `warpbags train --set`",
                         json_help="also write every row's numbers here")
    args = parser.parse_args()
    torch.set_num_threads(1)
    check_options([(0 < args.pose_lr < math.inf,  # a NaN fails both comparisons
                    f"--pose-lr must be a positive number, got {args.pose_lr:g}"),
                   procrustes_views_check(str(args.views), args.views)])
    check_json(args.json)
    fit_iters, start_noises = parse_numbers(args.fit_iters, "--fit-iters", int), parse_start_noise(args.start_noise)
    sizes = {} if args.max_image_size is None else {"max_image_size": args.max_image_size}
    # a bad setting fails before the header
    overrides = training_overrides(args, fixed=FIXED, runs=[(f"the fits of --views {args.views}",
                                                             run_settings(args.views, fit_iters, sizes))])
    overrides.update(sizes)
    scenes = {name: open_bench_scene(name) for name in args.scenes}  # a bad name fails before the table's header
    check_view_counts(scenes, [args.views])
    print(f"{'scene':<22} {'views':>5} {'px':>5} {'fit its':>8} {'start noise':>11} {'rot start':>9} {'rot mean':>10}"
          f" {'rot max':>8} {'centre floor':>12} {'centres % orbit':>14} {'min':>8}")
    rows = []
    for name, scene in scenes.items():
        rows += run_scene(name, scene, args.views, fit_iters, args.pose_iters, args.pose_lr, args.preset, overrides,
                          start_noises, args.optimizer)
    if args.json:
        write_json(args.json, rows, indent=2)


if __name__ == "__main__":
    clean_errors(main)()  # a bad scene name or setting: one line and exit code 2, as the CLI
