"""Pose-recovery accuracy table: BAGS from noisy poses over noise levels, view counts and noise seeds, next to the
true-pose model, plus an ablation of each part of the pose pipeline, in one run.

    python bench/pose_recovery.py SCENE [SCENE ...] [--rot 5,10,15,20,30] [--trans 0.3] [--views 4,6,9]
        [--seeds 0,1,2] [--variants bags,fixed-noisy] [--ablations] [--preset quick] [--set NAME=VALUE ...]
        [--depth true|monocular|none] [--start-only] [--json bench/results/pose_recovery.json]

SCENE: a preset (maryrose, moldgoldcape: a clone under WARPBAGS_DATA, synthetic, synthetic-tele), a scene folder,
`synthetic-small` (16 views, 96 px, cached) or `synthetic-tele-small` (16 views, 128 px, maryrose's 18.6 deg field of
view and framing, cached; `synthetic-tele-256`: the same at 256 px; `synthetic-tele-lit`: the same with the light and
the colour gains changing from view to view; `synthetic-tele-turntable`: lit as on a turntable, the light turning
with the camera; `synthetic-tele-tankard`: a wooden tankard shaped and textured like maryrose's instead of the
excavator). Every
training camera is perturbed (rotation angle ~ N(0, rot^2) deg about a random axis, each camera-centre coordinate
~ N(0, trans^2) in scene units, orbit radius 4) and optimized (free gauge); errors are measured after sim(3)
Procrustes alignment. Variants:
    bags          the method (the preset as shipped)
    fixed-noisy   the same pipeline with the noisy poses frozen (GaussianObject's baseline)
    truth-start   bags started at the reference poses (no noise): where the method's own optimum sits on the scene
    frozen-orbit  bags with the orbit about the object centre held in every round (`camera.orbit_from_round`)
    --ablations   bags with one part switched off in turn: no-centroid-start, no-coherence (no silhouette-
                  coherence solve of the starting poses), no-silhouette (mask distance and
                  chamfer terms), no-precondition, camera-param (se(3) about the camera centre, no preconditioner),
                  poses-whole-round and poses-first-half (the pose window of each round, instead of from a quarter
                  of the round to its end), no-hypotheses (no turns of the worst-fit camera tried in round 2),
                  no-average (the last pose estimate instead of the mean of the last round's)
--depth: the depth maps training sees. `true`: the scene's own (a synthetic scene's are exact, which no capture
has); `monocular`: those degraded once per scene as a monocular network's would be (relative, smooth shape errors of
20% of the object's relief, soft edges: `warpbags.data.noise.monocular_like_depths`); `none`: no depth maps, as a
capture without them (maryrose ships none). The depth term is GaussianObject's, invariant to scale and shift.
A true-pose model (poses frozen at the truth) is trained once per scene, view count and seed, for the PSNR/SSIM it
reaches. Per row, means over the seeds: the rotation noise as injected (no alignment) and the given poses' error
after Procrustes on their noisy centres, the rotation error of the poses training starts from (after the
mask-centroid start and the silhouette-coherence solve), mean rotation error (deg) at the end, each run's worst
camera and the worst of all, mean translation error (% of the orbit radius), the share of cameras ending under 1 deg,
the rotation error the camera centres alone force (the centre floor, at the given poses and at the end), how far the pose errors move the object in the images (RMS pixels at the
training resolution over the trained Gaussians' opaque centres, given poses -> end), held-out PSNR/SSIM (test cameras aligned by the same sim(3)) and
PSNR* after 50 iterations of test-pose refinement, and minutes of training iterations per run (the start
procedures and the evaluation not included). `--start-only` trains nothing and reports
the starting poses alone (seconds a run): what the silhouettes give before any Gaussian is fitted.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch

from common import (add_training_options, check_json, check_options, check_view_counts, merge_settings,
                    open_bench_scene, pose_noise_checks, procrustes_views_check, quiet_trainer, timed_training,
                    training_overrides, with_depth, write_json)
from warpbags.alignment import pose_errors
from warpbags.data import ORBIT_RADIUS
from warpbags.evaluation import evaluate_run
from warpbags.cli.common import clean_errors, parse_numbers

VARIANTS = {
    "bags": {},
    "fixed-noisy": dict(pose_opt=False),
    "no-centroid-start": dict(camera={"centroid_start": False}),
    "no-coherence": dict(camera={"coherence_iters": 0}),
    "no-silhouette": dict(lambda_mask_distance=0.0, lambda_chamfer=0.0),
    "no-precondition": dict(camera={"precondition": False}),
    "camera-param": dict(camera={"parameterization": "camera", "precondition": False}),
    "poses-whole-round": dict(pose_round_window=(0.0, 1.0)),
    "poses-first-half": dict(pose_round_window=(0.0, 0.5)),
    # no noise, poses optimized all the same: how far the method moves cameras that start at the reference poses
    "truth-start": dict(rot_noise_deg=0.0, trans_noise=0.0),
    # the object-centric orbit held in every round (any value >= the preset's rounds)
    "frozen-orbit": dict(camera={"orbit_from_round": 99}),
    # no search over turns of the worst-fit camera (`camera.hypotheses_round`)
    "no-hypotheses": dict(camera={"hypotheses_round": 0}),
    # the last pose estimate kept instead of the mean of the last round's (`camera.average_share`)
    "no-average": dict(camera={"average_share": 0.0}),
    # the feature matches' epipolar residual in the coherence solve and the rounds (`warpbags.correspondences`)
    "matches": dict(lambda_epipolar=0.01, camera={"coherence_epipolar": 1e-3}),
}
ABLATIONS = ["no-centroid-start", "no-coherence", "no-silhouette", "no-precondition", "camera-param", "poses-whole-round",
             "poses-first-half", "no-hypotheses", "no-average"]


def run_settings(overrides: dict, variant: str, views: int, rot: float, trans: float, seed: int) -> dict:
    """The settings of one run of `variant`: the noise of `rot` / `trans` drawn with `seed`, trained with `seed`, no
    repair stage, the variant's own settings on top."""
    settings = merge_settings(overrides, dict(views=views, rot_noise_deg=rot, trans_noise=trans, noise_seed=seed,
                                              seed=seed, repair={"iters": 0}))
    return merge_settings(settings, VARIANTS[variant])


def true_pose_settings(overrides: dict, views: int, seed: int) -> dict:
    """The settings of the true-pose model: the scene's poses, frozen, trained with `seed`, no repair stage."""
    return merge_settings(overrides, dict(views=views, seed=seed, pose_opt=False, repair={"iters": 0}))


def run_once(scene, settings: dict, preset: str, root: Path, train: bool = True) -> dict:
    """Train and evaluate one configuration; returns its pose errors, image metrics and minutes. The poses training
    starts from (after the mask-centroid start and the silhouette-coherence solve) are measured too; with `train`
    False only those, without training."""
    trainer = quiet_trainer(scene, settings, preset, root)
    truth = trainer.viewmats_true.double().cpu()
    start = pose_errors(trainer.viewmats_start.double().cpu(), truth, alignment="procrustes")
    # the noise as injected, in the true frame: each camera's noise angle (Procrustes on the noisy centres adds the
    # tilt of the rig they fit to it)
    injected = pose_errors(trainer.viewmats_init.double().cpu(), truth, alignment="none")["rotation_errors_deg"].tolist()
    if not train:
        initial = pose_errors(trainer.viewmats_init.double().cpu(), truth, alignment="procrustes")
        return {"rotation_injected": injected, "rotation_initial": initial["rotation_errors_deg"].tolist(),
                "rotation_start": start["rotation_errors_deg"].tolist(),
                "translation_initial": initial["translation_errors"].tolist(),
                "translation_start": start["translation_errors"].tolist()}
    minutes = timed_training(trainer)
    report = evaluate_run(root, refine_iters=50, log=lambda message: None)
    poses = report["poses"]["procrustes"]
    return {
        "rotation_injected": injected,
        "rotation_initial": poses["initial"]["rotation_deg"], "rotation_start": start["rotation_errors_deg"].tolist(),
        "rotation_final": poses["final"]["rotation_deg"],
        "translation_initial": poses["initial"]["translation"], "translation_start": start["translation_errors"].tolist(),
        "translation_final": poses["final"]["translation"],
        "floor_initial": poses["initial"]["rotation_deg_centre_floor"],
        "floor_final": poses["final"]["rotation_deg_centre_floor"],
        "pixels_initial": poses["initial"]["reprojection_px"], "pixels_final": poses["final"]["reprojection_px"],
        "psnr": report["images"]["mean"]["psnr"], "ssim": report["images"]["mean"]["ssim"],
        "psnr_refined": report["images_after_test_pose_refinement"]["mean"]["psnr"], "minutes": minutes,
    }


def summarize(runs: list[dict]) -> dict:
    """Means over noise seeds of the per-run statistics (of the starting poses only, for runs not trained)."""
    def mean(values):
        return float(np.mean(values))
    row = {
        "rot_injected": mean([np.mean(r["rotation_injected"]) for r in runs]),
        "rot_init": mean([np.mean(r["rotation_initial"]) for r in runs]),
        "rot_start": mean([np.mean(r["rotation_start"]) for r in runs]),
        "rot_start_per_seed": [float(np.mean(r["rotation_start"])) for r in runs],
        "trans_init_pct": mean([100 * np.mean(r["translation_initial"]) / ORBIT_RADIUS for r in runs]),
        "trans_start_pct": mean([100 * np.mean(r["translation_start"]) / ORBIT_RADIUS for r in runs]),
    }
    if "rotation_final" not in runs[0]:
        return row
    return {
        **row,
        "rot_mean": mean([np.mean(r["rotation_final"]) for r in runs]),
        "rot_per_seed": [float(np.mean(r["rotation_final"])) for r in runs],
        "rot_max": mean([np.max(r["rotation_final"]) for r in runs]),
        "rot_worst": float(max(np.max(r["rotation_final"]) for r in runs)),
        "floor_init": mean([np.mean(r["floor_initial"]) for r in runs]),
        "floor": mean([np.mean(r["floor_final"]) for r in runs]),
        "trans_pct": mean([100 * np.mean(r["translation_final"]) / ORBIT_RADIUS for r in runs]),
        "px_init": mean([np.mean(r["pixels_initial"]) for r in runs]),
        "px": mean([np.mean(r["pixels_final"]) for r in runs]),
        "under_1deg": mean([np.mean(np.array(r["rotation_final"]) < 1.0) for r in runs]),
        "psnr": mean([r["psnr"] for r in runs]), "ssim": mean([r["ssim"] for r in runs]),
        "psnr_refined": mean([r["psnr_refined"] for r in runs]), "minutes": mean([r["minutes"] for r in runs]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--rot", default="15", help="rotation noise stds, degrees, comma-separated")
    parser.add_argument("--trans", type=float, default=0.3, help="camera-centre noise std per axis (orbit radius 4)")
    parser.add_argument("--views", default="4", help="training view counts, comma-separated, each 3 or more (the "
                                                      "errors are after Procrustes alignment of the camera centres)")
    parser.add_argument("--seeds", default="0,1,2", help="noise seeds, comma-separated")
    parser.add_argument("--variants", default="bags", help=f"comma-separated, of {', '.join(VARIANTS)}")
    parser.add_argument("--ablations", action="store_true", help="add " + ", ".join(ABLATIONS))
    parser.add_argument("--no-true-pose", action="store_true", help="skip the true-pose reference model")
    parser.add_argument("--start-only", action="store_true",
                        help="no training: only the poses training would start from (after the mask-centroid start "
                             "and the silhouette-coherence solve), in seconds a run")
    parser.add_argument("--depth", choices=("true", "monocular", "none"), default="true",
                        help="depth maps seen in training: the scene's, degraded as a monocular network's, or none")
    add_training_options(parser, "a TrainConfig field for every run (repeatable), as `warpbags train --set`",
                         json_help="also write every run's numbers here")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rots, view_counts = parse_numbers(args.rot, "--rot"), parse_numbers(args.views, "--views", int)
    check_options(check for rot in rots for check in pose_noise_checks(rot, args.trans))
    check_options([procrustes_views_check(repr(args.views), min(view_counts))])
    check_json(args.json)
    seeds = parse_numbers(args.seeds, "--seeds", int)
    variants = args.variants.split(",") + (ABLATIONS if args.ablations else [])
    unknown = [name for name in variants if name not in VARIANTS]
    if unknown:
        parser.error(f"unknown variant {unknown[0]!r}; choose from {', '.join(VARIANTS)}")
    # a bad preset or setting fails before the first line of the table
    overrides = training_overrides(args, fixed={"views": "from --views", "rot_noise_deg": "from --rot",
                                                "trans_noise": "from --trans", "noise_seed": "from --seeds",
                                                "seed": "from --seeds", "repair.iters": "0: no repair stage",
                                                "rot_noise_fixed": "a normal angle of std --rot",
                                                "camera.fix_first_camera": "every camera perturbed",
                                                "pose_opt": "from --variants"},
                                   runs=[*((f"--variants {variant}: its settings {VARIANTS[variant]}",
                                            run_settings({}, variant, views, rot, args.trans, seed))
                                           for variant in variants for views in view_counts for rot in rots
                                           for seed in seeds),
                                         *(("the true-pose model (poses frozen; --no-true-pose skips it)",
                                            true_pose_settings({}, views, seed))
                                           for views in view_counts for seed in seeds
                                           if not (args.no_true_pose or args.start_only))])
    scenes = {name: with_depth(open_bench_scene(name), args.depth) for name in args.scenes}
    check_view_counts(scenes, view_counts)
    results: dict = {"preset": args.preset, "overrides": overrides, "trans_noise": args.trans, "depth": args.depth,
                     "seeds": seeds, "rows": []}
    per_seed_width = max(len("per seed"), 6 * len(seeds) - 1)
    if args.start_only:
        header = (f"{'scene':<20} {'views':>5} {'noise':>9} {'variant':<18} {'injected':>8} {'rot init':>8} {'rot start':>9} "
                  f"{'per seed':<{per_seed_width}} {'t init %':>8} {'t start %':>9}")
    else:
        header = (f"{'scene':<20} {'views':>5} {'noise':>9} {'variant':<18} {'injected':>8} {'rot init':>8} {'start':>6} "
                  f"{'rot mean':>8} {'per seed':<{per_seed_width}} {'rot max':>8} {'worst':>6} {'<1 deg':>6} {'floor':>13} "
                  f"{'t init %':>8} {'t %':>6} "
                  f"{'px':>13} {'PSNR':>6} {'SSIM':>6} {'PSNR*':>6} {'true PSNR':>9} {'min':>5}")
    print(f"preset {args.preset}, overrides {overrides}, seeds {args.seeds}, translation noise {args.trans} "
          f"({100 * args.trans / ORBIT_RADIUS:.1f}% of the orbit radius per axis), depth maps: {args.depth}")
    print(header + "\n" + "-" * len(header), flush=True)
    with tempfile.TemporaryDirectory() as root:
        for scene_name, scene in scenes.items():
            for views in view_counts:
                true_pose = {}
                if not (args.no_true_pose or args.start_only):
                    for seed in seeds:
                        true_pose[seed] = run_once(scene, true_pose_settings(overrides, views, seed), args.preset,
                                                   Path(root) / f"{scene_name}-{views}-true-{seed}")
                true_psnr = float(np.mean([r["psnr"] for r in true_pose.values()])) if true_pose else float("nan")
                for rot in rots:
                    for variant in variants:
                        if "rot_noise_deg" in VARIANTS[variant] and rot != rots[0]:
                            continue  # a variant with its own noise (truth-start) runs once, not once per --rot
                        runs = []
                        for seed in seeds:
                            settings = run_settings(overrides, variant, views, rot, args.trans, seed)
                            folder = Path(root) / f"{scene_name}-{views}-{rot}-{variant}-{seed}"
                            runs.append({"seed": seed, **run_once(scene, settings, args.preset, folder,
                                                                  train=not args.start_only)})
                        row = summarize(runs)
                        # the noise the runs had: a variant may set its own (truth-start: none)
                        noise = dict(rot_noise=settings["rot_noise_deg"], trans_noise=settings["trans_noise"])
                        results["rows"].append({"scene": scene_name, "views": views, **noise, "variant": variant,
                                                "true_psnr": true_psnr, **row, "runs": runs})
                        noise_label = f"{noise['rot_noise']:g}/{noise['trans_noise']:g}"
                        label = f"{scene_name:<20} {views:>5} {noise_label:>9} {variant:<18} "
                        if args.start_only:
                            print(label + f"{row['rot_injected']:>8.2f} {row['rot_init']:>8.2f} {row['rot_start']:>9.3f} "
                                  f"{' '.join(f'{v:5.2f}' for v in row['rot_start_per_seed']):<{per_seed_width}} "
                                  f"{row['trans_init_pct']:>8.2f} {row['trans_start_pct']:>9.2f}", flush=True)
                        else:
                            floor = f"{row['floor_init']:.2f} -> {row['floor']:.2f}"
                            pixels = f"{row['px_init']:.2f} -> {row['px']:.2f}"
                            print(label + f"{row['rot_injected']:>8.2f} {row['rot_init']:>8.2f} {row['rot_start']:>6.2f} "
                                  f"{row['rot_mean']:>8.3f} "
                                  f"{' '.join(f'{v:5.2f}' for v in row['rot_per_seed']):<{per_seed_width}} "
                                  f"{row['rot_max']:>8.3f} {row['rot_worst']:>6.2f} "
                                  f"{100 * row['under_1deg']:>5.0f}% {floor:>13} "
                                  f"{row['trans_init_pct']:>8.2f} {row['trans_pct']:>6.2f} {pixels:>13} "
                                  f"{row['psnr']:>6.2f} {row['ssim']:>6.3f} {row['psnr_refined']:>6.2f} {true_psnr:>9.2f} "
                                  f"{row['minutes']:>5.1f}", flush=True)
                        if args.json:
                            write_json(args.json, results)
    print("rotation in degrees and translation in % of the orbit radius, after sim(3) Procrustes alignment, means over\n"
          "noise seeds (per seed: each seed's mean, in the order given; rot max: each run's worst camera, averaged over\n"
          "the seeds; worst: the worst camera of all the runs); injected: the rotation noise as injected (each camera's\n"
          "noise angle, no alignment); rot init: the given poses after Procrustes on their noisy centres, which adds the\n"
          "tilt of the rig fitted to them; start: the poses training starts from, after the mask-centroid start and the\n"
          "silhouette-coherence solve; floor: the rotation error the camera centres alone force\n"
          "(alignment.centre_floor_errors), at the given poses and at the end; min: minutes of training iterations per run;\n"
          "px: how far the pose errors move the object in the images (RMS pixels at the training resolution over the\n"
          "trained Gaussians' opaque centres, alignment.reprojection_errors), given poses -> end;\n"
          "PSNR/SSIM on held-out views with aligned test cameras, PSNR* after 50 test-pose refinement iterations; true\n"
          "PSNR: the baseline's schedule (one round of the preset's iterations) on the true poses, frozen, without\n"
          "test-pose refinement.")


if __name__ == "__main__":
    clean_errors(main)()  # a bad scene name or setting: one line and exit code 2, as the CLI
