"""Does the training loss single out the reference poses? Gaussians fitted with the poses frozen at a pose set.

    python bench/fitted_loss.py SCENE [SCENE ...] [--seeds 0,1,2] [--rot 15] [--trans 0.3] [--views 4]
        [--depth true|monocular|none] [--fit-seeds 0,1] [--preset quick] [--set NAME=VALUE ...] [--json PATH]

SCENE: as bench/pose_recovery.py (a preset, a folder, or one of its small synthetic scenes). For each scene and noise
seed the preset first recovers the poses from the noise, as bench/pose_recovery.py's `bags` variant does, keeping
the poses training starts from (after the mask-centroid start and the silhouette-coherence solve) and those it ends
at. Then at each pose set - the reference poses, and each seed's start and end - the preset's Gaussians are fitted
with the poses frozen there (one fit per --fit-seeds value, the numbers averaged), and two things are measured over
all training views:

- the training loss at the fit's end: the terms and weights training minimizes, at its last iteration's settings.
  If Gaussians fitted at poses several degrees off reach the loss they reach at the reference, the loss does not
  single the reference out, and no schedule of a joint fit can find it;
- the images' consistency across views (`cross_view_consistency`): each view's target image carried into every
  other view through the fitted Gaussians' depth, compared where it lands on that view's object: the mean L1 of the
  colours and the mean local normalized cross-correlation of their grey levels. Gaussians seen by one view can
  follow its camera; this measure cannot be fitted that way.

Rotation errors are after sim(3) Procrustes alignment of the camera centres, as everywhere in the benchmarks.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from common import (add_training_options, check_json, check_options, check_view_counts, merge_settings,
                    open_bench_scene, pose_noise_checks, procrustes_views_check, training_overrides, with_depth,
                    write_json)
from warpbags.alignment import pose_errors
from warpbags.cameras import pixel_directions, project_points
from warpbags.cli.common import clean_errors, parse_numbers
from warpbags.configs.train import load_preset
from warpbags.errors import WarpbagsError
from warpbags.trainer import Trainer, training_scene


def _box_mean(values: torch.Tensor, weights: torch.Tensor, radius: int) -> torch.Tensor:
    """The weighted mean of [H,W] `values` over (2 radius + 1)^2 windows (weights [H,W])."""
    size = 2 * radius + 1
    pool = lambda x: F.avg_pool2d(x[None, None], size, stride=1, padding=radius, count_include_pad=False)[0, 0]
    return pool(values * weights) / pool(weights).clamp_min(1e-12)


def cross_view_consistency(images: torch.Tensor, masks: torch.Tensor, depths: torch.Tensor, viewmats: torch.Tensor,
                           Ks: torch.Tensor, depth_tolerance: float = 0.02, radius: int = 3) -> list[dict]:
    """Each view's image carried into every other view through its depth map, compared where it lands.

    Every pixel of view i inside its mask (> 0.5) with a depth is lifted to the world by `depths[i]` (z-depth) and
    projected into view j; it counts where it lands inside view j's frame and mask and in front of nothing (its
    depth within `depth_tolerance` of `depths[j]` there, relatively). There view i's colour is compared with view
    j's, sampled bilinearly.

    Args:
        images: [C,H,W,3] in [0, 1]. masks: [C,H,W]. depths: [C,H,W] z-depths (0 = none). viewmats: [C,4,4]
            world-to-camera. Ks: [C,3,3]. radius: the half-size of the correlation's windows, pixels.

    Returns:
        one dict per ordered pair (i != j): "i", "j", "pixels" (how many count), "l1" (mean absolute colour
        difference, averaged over channels) and "ncc" (the mean, over counted pixels at least 80% of whose window
        counts and whose grey levels vary there in both views, of the windows' normalized cross-correlation, their
        counted pixels weighted alike); l1 and ncc are nan under 20 pixels, ncc also under 10 such windows.
    """
    count, height, width, _ = images.shape
    rows, cols = torch.meshgrid(torch.arange(height, dtype=images.dtype), torch.arange(width, dtype=images.dtype),
                                indexing="ij")
    pixels = torch.stack([cols + 0.5, rows + 0.5], -1).reshape(-1, 2)
    grey = images.mean(-1)
    pairs = []
    for i in range(count):
        points_camera = pixel_directions(pixels, Ks[i]) * depths[i].reshape(-1, 1)
        rotation, translation = viewmats[i, :3, :3], viewmats[i, :3, 3]
        points = (points_camera - translation) @ rotation  # R^T (x - t): to the world
        source = (masks[i].reshape(-1) > 0.5) & (depths[i].reshape(-1) > 0)
        for j in range(count):
            if j == i:
                continue
            landed, z = project_points(viewmats[j:j + 1], Ks[j:j + 1], points)
            landed, z = landed[0], z[0]
            grid = torch.stack([2 * landed[:, 0] / width - 1, 2 * landed[:, 1] / height - 1], -1)

            def sample(image: torch.Tensor) -> torch.Tensor:  # [H,W,D] of view j at the landed points -> [H*W,D]
                sampled = F.grid_sample(image.permute(2, 0, 1)[None], grid.reshape(1, height, width, 2),
                                        align_corners=False, padding_mode="border")
                return sampled[0].permute(1, 2, 0).reshape(-1, image.shape[-1])

            colors = sample(images[j])
            depth_there, mask_there = sample(depths[j][..., None])[:, 0], sample(masks[j][..., None])[:, 0]
            inside = (landed[:, 0] > 0) & (landed[:, 0] < width) & (landed[:, 1] > 0) & (landed[:, 1] < height)
            counted = (source & inside & (z > 0) & (mask_there > 0.5)
                       & ((z - depth_there).abs() < depth_tolerance * z))
            number = int(counted.sum())
            pair = {"i": i, "j": j, "pixels": number, "l1": float("nan"), "ncc": float("nan")}
            if number >= 20:
                pair["l1"] = (images[i].reshape(-1, 3) - colors).abs().mean(-1)[counted].mean().item()
                weights = counted.to(images.dtype).reshape(height, width)
                here, there = grey[i], colors.mean(-1).reshape(height, width)
                mean_here, mean_there = _box_mean(here, weights, radius), _box_mean(there, weights, radius)
                var_here = _box_mean(here * here, weights, radius) - mean_here**2
                var_there = _box_mean(there * there, weights, radius) - mean_there**2
                covariance = _box_mean(here * there, weights, radius) - mean_here * mean_there
                ncc = covariance / (var_here.clamp_min(1e-12) * var_there.clamp_min(1e-12)).sqrt()
                mostly = F.avg_pool2d(weights[None, None], 2 * radius + 1, stride=1, padding=radius,
                                      count_include_pad=True)[0, 0] >= 0.8
                valid = counted.reshape(height, width) & mostly & (var_here > 1e-5) & (var_there > 1e-5)
                if valid.sum() > 10:
                    pair["ncc"] = ncc[valid].mean().item()
            pairs.append(pair)
    return pairs


def fit_settings(fit_seed: int) -> dict:
    """This script's settings of a fit at a pose set (on top of `--set` and the view count): the poses frozen,
    trained with `fit_seed`, no repair stage."""
    return dict(pose_opt=False, seed=fit_seed, repair={"iters": 0})


def recovery_settings(rot: float, trans: float, seed: int) -> dict:
    """This script's settings of a pose recovery run (on top of `--set` and the view count): the noise of `rot` /
    `trans` drawn with `seed`, trained with `seed`, no repair stage, as bench/pose_recovery.py's `bags` variant."""
    return dict(rot_noise_deg=rot, trans_noise=trans, noise_seed=seed, seed=seed, repair={"iters": 0})


def fitted_at(scene, poses: torch.Tensor, settings: dict, preset: str, fit_seed: int) -> dict:
    """Fit the preset's Gaussians with the training cameras frozen at [C,4,4] `poses`; the training loss over all
    views at the end, its terms, and the images' consistency across views through the fitted depth."""
    config = load_preset(preset, **merge_settings(settings, fit_settings(fit_seed)))
    with tempfile.TemporaryDirectory() as out:
        trainer = Trainer(training_scene(scene, config), config, out, viewmats_init=poses, log=lambda message: None)
        trainer.train()
        views = torch.arange(trainer.num_cameras, device=trainer.device)
        viewmats = trainer.current_viewmats().detach()
        step = trainer.schedule.at(trainer.iteration - 1)
        loss, terms, _ = trainer.model.loss(views, viewmats, step)  # with the graph: it retains a gradient
        with torch.no_grad():
            renders, alphas, _ = trainer.model.render(views, viewmats, step.sh_degree, depth=True)
        data = trainer.model.training_views
        depths = torch.where(alphas[..., 0] > 0.5, renders[..., 3], torch.zeros_like(renders[..., 3]))
        pairs = cross_view_consistency(data.images.cpu(), data.masks.cpu(), depths.cpu(), viewmats.cpu(),
                                       data.Ks.cpu())
    return {"loss": loss.item(), "terms": terms, "pixels": float(np.mean([p["pixels"] for p in pairs])),
            "l1": float(np.nanmean([p["l1"] for p in pairs])), "ncc": float(np.nanmean([p["ncc"] for p in pairs]))}


def recovered_poses(scene, settings: dict, preset: str, root: Path) -> tuple[torch.Tensor, torch.Tensor]:
    """Pose recovery from the noise of `settings`: ([C,4,4] poses it starts from, [C,4,4] poses it ends at)."""
    config = load_preset(preset, **settings)
    trainer = Trainer(training_scene(scene, config), config, root, log=lambda message: None)
    start = trainer.viewmats_start.detach().clone()
    trainer.train()
    return start, trainer.current_viewmats().detach().clone()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--seeds", default="0,1,2", help="noise seeds of the pose recovery runs, comma-separated")
    parser.add_argument("--rot", type=float, default=15.0, help="rotation noise std, degrees")
    parser.add_argument("--trans", type=float, default=0.3, help="camera-centre noise std per axis (orbit radius 4)")
    parser.add_argument("--views", type=int, default=4, help="training views, 3 or more (the rotation errors are "
                                                                 "after Procrustes alignment of the camera centres)")
    parser.add_argument("--depth", choices=("true", "monocular", "none"), default="true",
                        help="the scene's depth maps, degraded as a monocular network's, or none")
    parser.add_argument("--fit-seeds", default="0,1", help="training seeds of the frozen fits, averaged")
    add_training_options(parser, "a TrainConfig field for every run and fit (repeatable), as `warpbags train --set`",
                         json_help="also write every fit's numbers here")
    args = parser.parse_args()
    torch.set_num_threads(1)
    seeds, fit_seeds = parse_numbers(args.seeds, "--seeds", int), parse_numbers(args.fit_seeds, "--fit-seeds", int)
    check_options(pose_noise_checks(args.rot, args.trans))
    check_options([procrustes_views_check(str(args.views), args.views)])
    check_json(args.json)
    # a bad preset or setting, in every run and fit, fails before the first line of the table
    overrides = training_overrides(args, fixed={"views": "from --views", "rot_noise_deg": "from --rot",
                                                "trans_noise": "from --trans", "noise_seed": "from --seeds",
                                                "seed": "from --seeds and --fit-seeds",
                                                "pose_opt": "on to recover the poses, off for the fits",
                                                "repair.iters": "0: no repair stage"},
                                   runs=[(f"--views {args.views}", dict(views=args.views)),
                                         *((f"the pose recovery of --seeds {seed}",
                                            dict(views=args.views, **recovery_settings(args.rot, args.trans, seed)))
                                           for seed in seeds),
                                         *((f"the fit of --fit-seeds {seed}",
                                            dict(views=args.views, **fit_settings(seed))) for seed in fit_seeds)])
    scenes = {name: with_depth(open_bench_scene(name), args.depth) for name in args.scenes}
    check_view_counts(scenes, [args.views])
    for name, scene in scenes.items():
        if scene.masks is None:
            raise WarpbagsError(f"scene {name} has no masks: the comparison across views counts pixels on the object")
    results: dict = {"preset": args.preset, "overrides": overrides, "depth": args.depth, "views": args.views,
                     "rot_noise": args.rot, "trans_noise": args.trans, "seeds": seeds, "fit_seeds": fit_seeds,
                     "rows": []}
    header = (f"{'scene':<24} {'poses':<14} {'rot (deg)':>9} {'loss':>9} {'vs ref':>7} {'px/pair':>7} {'L1':>7} "
              f"{'NCC':>6} {'min':>5}")
    print(f"preset {args.preset}, overrides {overrides}, {args.views} views, noise {args.rot:g} deg / {args.trans:g}, "
          f"depth maps: {args.depth}, fits averaged over training seeds {args.fit_seeds}")
    print(header + "\n" + "-" * len(header), flush=True)
    base = merge_settings(overrides, dict(views=args.views))
    with tempfile.TemporaryDirectory() as root:
        for name, scene in scenes.items():
            truth = training_scene(scene, load_preset(args.preset, **base)).viewmats
            pose_sets = [("reference", None, truth)]
            for seed in seeds:
                settings = merge_settings(base, recovery_settings(args.rot, args.trans, seed))
                start, end = recovered_poses(scene, settings, args.preset, Path(root) / f"{name}-{seed}")
                pose_sets += [(f"seed {seed} start", seed, start), (f"seed {seed} end", seed, end)]
            reference_loss = None
            for label, seed, poses in pose_sets:
                started = time.perf_counter()
                fits = [fitted_at(scene, poses, base, args.preset, fit_seed) for fit_seed in fit_seeds]
                rotation = pose_errors(poses.double().cpu(), truth.double().cpu(),
                                       alignment="procrustes")["rotation_error_deg_mean"]
                row = {"scene": name, "poses": label, "noise_seed": seed, "rotation_deg": rotation,
                       **{key: float(np.mean([fit[key] for fit in fits])) for key in ("loss", "pixels", "l1", "ncc")},
                       "fits": fits, "minutes": (time.perf_counter() - started) / 60}
                reference_loss = row["loss"] if reference_loss is None else reference_loss
                row["vs_reference_pct"] = 100 * (row["loss"] / reference_loss - 1)
                results["rows"].append(row)
                print(f"{name:<24} {label:<14} {rotation:>9.2f} {row['loss']:>9.5f} {row['vs_reference_pct']:>+6.1f}% "
                      f"{row['pixels']:>7.0f} {row['l1']:>7.4f} {row['ncc']:>6.3f} {row['minutes']:>5.1f}", flush=True)
                if args.json:
                    write_json(args.json, results)
    print("rot: the pose set's mean rotation error after sim(3) Procrustes alignment; loss: the training loss over all\n"
          "views of Gaussians fitted with the poses frozen there (vs ref: relative to the reference poses'); px/pair,\n"
          "L1, NCC: each view's image carried into the others through the fitted depth (pixels counted per ordered pair,\n"
          "mean colour L1, mean local normalized cross-correlation); min: minutes of the fits.")


if __name__ == "__main__":
    clean_errors(main)()  # a bad scene name or setting: one line and exit code 2, as the CLI
