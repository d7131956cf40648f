"""Do a scene's views agree with its reference poses? Leave-one-out registration, view by view.

    python bench/view_agreement.py SCENE [SCENE ...] [--views 9] [--sizes 128,256] [--fit-iters 200]
        [--refine-iters 60] [--depth true|none] [--preset quick] [--set NAME=VALUE ...] [--json PATH]

SCENE: as bench/pose_recovery.py (a preset, a folder, `synthetic-small` or `synthetic-tele-small`). For each
training view in turn, Gaussians are fitted for --fit-iters iterations to the *other* training views at their
reference poses (frozen; one round of the preset's schedule, as the repair stage's leave-one-out fits), then the
left-out camera alone is registered against them from its reference pose by --refine-iters L-BFGS iterations of
the photometric loss (`warpbags.evaluation.refine_poses`, the test-pose refinement). The other cameras stay at the
reference, so the registered pose needs no alignment: its distance from the reference (rotation in degrees, centre
in % of the orbit radius) is how far that view's own pixels put it from the pose the others imply.

Where a joint run starts at the reference and drifts (bench/pose_recovery.py's truth-start) this tells the model's
pull from the data's: on a synthetic scene every view registers within a fraction of a degree, so a drift there
is the joint optimization's; a real capture whose views register degrees from its reference (lighting that changed
between capture sequences, an object moved, wrong intrinsics) cannot be brought closer than that by photometric
bundle adjustment, whatever the optimizer. Run it on a capture before trusting its poses as ground truth, and at
several --sizes to see whether resolution closes the gap.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np
import torch

from common import (add_training_options, check_json, check_options, open_bench_scene, training_overrides,
                    with_depth, write_json)
from warpbags.alignment import pose_errors
from warpbags.configs.train import load_preset
from warpbags.data import ORBIT_RADIUS
from warpbags.evaluation import refine_poses
from warpbags.model import TrainingViews
from warpbags.repair.pairs import LeaveOneOutFit
from warpbags.trainer import training_scene
from warpbags.cli.common import clean_errors, parse_numbers


def register_left_out(views: TrainingViews, reference: torch.Tensor, left_out: int, config, fit_iters: int,
                      refine_iters: int) -> torch.Tensor:
    """[4, 4] the pose of view `left_out` registered against Gaussians fitted to the other views at `reference`."""
    others = [view for view in range(views.num_views) if view != left_out]
    fit = LeaveOneOutFit(config, TrainingViews.of(views.scene.subset(others), config, views.device), reference[others])
    fit.train_until(fit_iters, should_stop=lambda: False)
    one = slice(left_out, left_out + 1)
    return refine_poses(fit.model.params, reference[one], views.Ks[one], views.targets[one], views.scene.width,
                        views.scene.height, fit.schedule.sh_degree(fit_iters - 1), refine_iters)[0]


def view_agreement(scene, views: int, size: int, fit_iters: int, refine_iters: int, preset: str,
                   overrides: dict) -> dict:
    """Every training view registered against the others at `size` px: per-view rotation (deg) and centre (% of
    the orbit radius) distances from the reference, and the minutes it took."""
    config = load_preset(preset, **{**overrides, "views": views, "max_image_size": size, "iters": fit_iters,
                                    "rounds": 1, "pose_opt": False})
    config = dataclasses.replace(config, densify=dataclasses.replace(config.densify,
                                                                     stop=min(config.densify.stop, fit_iters)))
    subset = training_scene(scene, config)
    training_views = TrainingViews.of(subset, config, torch.device("cpu"))
    reference = subset.viewmats.float()
    started = time.perf_counter()
    registered = torch.stack([register_left_out(training_views, reference, view, config, fit_iters, refine_iters)
                              for view in range(subset.num_views)])
    errors = pose_errors(registered.double(), reference.double(), alignment="none")
    return {"rotation_deg": [float(e) for e in errors["rotation_errors_deg"]],
            "centre_pct": [100 * float(e) / ORBIT_RADIUS for e in errors["translation_errors"]],
            "minutes": (time.perf_counter() - started) / 60}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--views", type=int, default=9, help="training views (each left out in turn)")
    parser.add_argument("--sizes", default="128", help="image sizes (max side, px), comma-separated")
    parser.add_argument("--fit-iters", type=int, default=200, help="iterations of each leave-one-out fit")
    parser.add_argument("--refine-iters", type=int, default=60, help="L-BFGS iterations of each registration")
    parser.add_argument("--depth", choices=("true", "none"), default="true",
                        help="the fits use the scene's depth maps (if it has any) or none")
    add_training_options(parser, "a TrainConfig field for every fit (repeatable), as `warpbags train --set`",
                         json_help="also write every view's numbers here")
    args = parser.parse_args()
    torch.set_num_threads(1)
    sizes = parse_numbers(args.sizes, "--sizes", int)
    # without a registration step every view stays at its reference: a row of zeros
    check_options([(args.refine_iters >= 1, f"--refine-iters must be >= 1, got {args.refine_iters}")])
    check_json(args.json)
    # a bad preset or setting fails before the first line of the table
    overrides = training_overrides(args, fixed={"views": "from --views", "max_image_size": "from --sizes",
                                                "iters": "from --fit-iters", "rounds": "1", "pose_opt": "off"},
                                   runs=[(f"the fit at --sizes {size} and --fit-iters {args.fit_iters}",
                                          dict(views=args.views, max_image_size=size, iters=args.fit_iters, rounds=1,
                                               pose_opt=False)) for size in sizes])
    scenes = {name: with_depth(open_bench_scene(name), args.depth) for name in args.scenes}
    rows = []
    header = f"{'scene':<20} {'views':>5} {'px':>5} {'rot mean':>8} {'median':>7} {'max':>7} {'centre %':>8}  per view (deg)"
    print(f"preset {args.preset}, overrides {overrides}, fit {args.fit_iters} iterations, "
          f"{args.refine_iters} L-BFGS iterations, depth maps: {args.depth}")
    print(header + "\n" + "-" * len(header), flush=True)
    for name, scene in scenes.items():
        for size in sizes:
            result = view_agreement(scene, args.views, size, args.fit_iters, args.refine_iters, args.preset, overrides)
            rotations = np.array(result["rotation_deg"])
            rows.append({"scene": name, "views": args.views, "size": size, **result})
            print(f"{name:<20} {args.views:>5} {size:>5} {rotations.mean():>8.2f} {np.median(rotations):>7.2f} "
                  f"{rotations.max():>7.2f} {np.mean(result['centre_pct']):>8.2f}  "
                  f"{', '.join(f'{r:.2f}' for r in rotations)}  ({result['minutes']:.1f} min)", flush=True)
            if args.json:
                write_json(args.json, {"fit_iters": args.fit_iters, "refine_iters": args.refine_iters,
                                       "depth": args.depth, "overrides": overrides, "rows": rows})
    print("each view registered by L-BFGS against Gaussians fitted to the other views at their reference poses;\n"
          "distances from its own reference pose: rotation in degrees, camera centre in % of the orbit radius")


if __name__ == "__main__":
    clean_errors(main)()  # a bad scene name or setting: one line and exit code 2, as the CLI
