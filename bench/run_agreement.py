"""Do runs that differ only in their training seed disagree where they are wrong? For each scene, view count and
noise seed, the poses are perturbed once (rotation noise of std --rot about random axes, centre noise --trans per
axis) and trained from there with each training seed; the table gives each run's error against the scene's poses
and how far the runs' final poses disagree with each other (`warpbags agree`'s measure), both after sim(3)
Procrustes alignment, so that the README can say what a disagreement tells a user who has no reference poses.

    python bench/run_agreement.py SCENE [SCENE ...] [--views 4,9] [--noise-seeds 0] [--train-seeds 0,1,2]
        [--rot 15] [--trans 0.3] [--depth true|monocular|none] [--preset quick] [--set NAME=VALUE ...] [--json F]

Columns (degrees unless named): error: the runs' mean rotation error (per run: each run's, in training-seed
order); disagree: the mean over pairs of runs and cameras of the angle between two runs' orientations of a camera;
error/disagree: their ratio; min: minutes of training a run. After each view count's rows, a line gives the
correlation over cameras (and noise seeds) of a camera's mean error with its mean disagreement (in the JSON:
"correlations"). SCENE: a preset (maryrose, moldgoldcape, ethiopianhead, ...), a scene folder or one of
bench/common.py's small synthetic scenes (synthetic-tele-small, ...).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch
from common import (add_training_options, check_json, check_options, check_view_counts, merge_settings,
                    open_bench_scene, pose_noise_checks, quiet_trainer, timed_training, training_overrides, with_depth,
                    write_json)

from warpbags.agreement import pose_agreement
from warpbags.cli.common import clean_errors, parse_numbers
from warpbags.errors import WarpbagsError
from warpbags.run_folder import load_run


def run_settings(views: int, rot: float, trans: float, noise_seed: int, seed: int) -> dict:
    """This script's settings of one run (on top of `--set`): the noise of `rot` / `trans` drawn with `noise_seed`,
    trained with `seed`, no repair stage."""
    return dict(views=views, rot_noise_deg=rot, trans_noise=trans, noise_seed=noise_seed, seed=seed,
                repair={"iters": 0})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--rot", type=float, default=15.0, help="rotation noise std, degrees")
    parser.add_argument("--trans", type=float, default=0.3, help="camera-centre noise std per axis (orbit radius 4)")
    parser.add_argument("--views", default="4", help="training view counts, comma-separated")
    parser.add_argument("--noise-seeds", default="0", help="noise seeds, comma-separated: one start each")
    parser.add_argument("--train-seeds", default="0,1,2", help="training seeds run from each start, comma-separated")
    parser.add_argument("--depth", choices=("true", "monocular", "none"), default="true",
                        help="depth maps seen in training: the scene's, degraded as a monocular network's, or none")
    add_training_options(parser, "a TrainConfig field for every run (repeatable), as `warpbags train --set`",
                         json_help="also write every run's numbers here")
    args = parser.parse_args()
    torch.set_num_threads(1)
    view_counts = parse_numbers(args.views, "--views", int, minimum=2)
    noise_seeds = parse_numbers(args.noise_seeds, "--noise-seeds", int)
    train_seeds = parse_numbers(args.train_seeds, "--train-seeds", int)
    if len(set(train_seeds)) < 2 or len(set(train_seeds)) < len(train_seeds):
        raise WarpbagsError(f"--train-seeds {args.train_seeds!r}: give two different seeds or more, each once, to "
                            "have runs to compare")
    if len(set(noise_seeds)) < len(noise_seeds):
        raise WarpbagsError(f"--noise-seeds {args.noise_seeds!r}: a seed given twice")
    check_options(pose_noise_checks(args.rot, args.trans))
    if args.rot <= 0 and args.trans <= 0:
        raise WarpbagsError("--rot 0 and --trans 0: without noise the scene's poses are no truth to measure errors by")
    check_json(args.json)
    overrides = training_overrides(args, fixed={"views": "from --views", "rot_noise_deg": "from --rot",
                                                "trans_noise": "from --trans", "noise_seed": "from --noise-seeds",
                                                "seed": "from --train-seeds", "repair.iters": "0: no repair stage"},
                                   runs=[(f"the run of --views {views}, noise seed {noise_seed}, training seed {seed}",
                                          run_settings(views, args.rot, args.trans, noise_seed, seed))
                                         for views in view_counts for noise_seed in noise_seeds
                                         for seed in train_seeds])
    scenes = {name: with_depth(open_bench_scene(name), args.depth) for name in args.scenes}
    check_view_counts(scenes, view_counts)
    results: dict = {"preset": args.preset, "overrides": overrides, "rot_noise": args.rot, "trans_noise": args.trans,
                     "depth": args.depth, "train_seeds": train_seeds, "noise_seeds": noise_seeds, "rows": [],
                     "correlations": []}
    header = (f"{'scene':<22} {'views':>5} {'noise seed':>10} {'error':>6} {'per run':<{6 * len(train_seeds)}} "
              f"{'disagree':>8} {'error/disagree':>14} {'min':>5}")
    print(f"preset {args.preset}, overrides {overrides}, noise {args.rot:g} deg / {args.trans:g}, depth maps: "
          f"{args.depth}, training seeds {args.train_seeds}")
    print(header + "\n" + "-" * len(header), flush=True)
    with tempfile.TemporaryDirectory() as root:
        for scene_name, scene in scenes.items():
            for views in view_counts:
                camera_errors, camera_disagreements = [], []
                for noise_seed in noise_seeds:
                    folders, minutes = [], []
                    for seed in train_seeds:
                        folder = Path(root) / f"{scene_name}-{views}-{noise_seed}-{seed}"
                        settings = merge_settings(overrides, run_settings(views, args.rot, args.trans, noise_seed,
                                                                          seed))
                        minutes.append(timed_training(quiet_trainer(scene, settings, args.preset, folder)))
                        folders.append(folder)
                    agreement = pose_agreement([load_run(folder) for folder in folders])
                    errors = agreement.error_deg  # [R, C], with the pairs' alignment
                    camera_errors.append(errors.mean(0))
                    camera_disagreements.append(agreement.rotation_deg.mean(0))
                    row = {"scene": scene_name, "views": views, "noise_seed": noise_seed, "alignment": agreement.alignment,
                           "error": float(errors.mean()), "error_per_run": errors.mean(1).tolist(),
                           "error_per_camera": errors.mean(0).tolist(),
                           "disagreement": float(agreement.rotation_deg.mean()),
                           "disagreement_per_camera": agreement.rotation_deg.mean(0).tolist(),
                           "agreement": agreement.to_json(), "minutes": float(np.mean(minutes))}
                    results["rows"].append(row)
                    per_run = " ".join(f"{value:5.2f}" for value in row["error_per_run"])
                    print(f"{scene_name:<22} {views:>5} {noise_seed:>10} {row['error']:>6.2f} "
                          f"{per_run:<{6 * len(train_seeds)}} {row['disagreement']:>8.2f} "
                          f"{row['error'] / max(row['disagreement'], 1e-9):>14.2f} {row['minutes']:>5.1f}", flush=True)
                    if args.json:
                        write_json(args.json, results)
                camera_errors, camera_disagreements = np.concatenate(camera_errors), np.concatenate(camera_disagreements)
                correlation = np.corrcoef(camera_errors, camera_disagreements)[0, 1]
                print(f"{'':<22} {views:>5} {'all':>10} cameras' error against their disagreement: correlation "
                      f"{correlation:.2f} over {len(camera_errors)} cameras", flush=True)
                results["correlations"].append({"scene": scene_name, "views": views, "correlation": float(correlation),
                                                "cameras": len(camera_errors)})
                if args.json:
                    write_json(args.json, results)
    print("error: rotation error against the scene's poses (deg, mean over cameras); disagree: angle between two "
          "runs' orientations of a camera (deg, mean over pairs and cameras); both after sim(3) Procrustes (SPARF's "
          "pairwise alignment with 2 views)")


if __name__ == "__main__":
    clean_errors(main)()
