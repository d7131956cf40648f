"""Pose recovery and novel-view quality: BAGS from noisy poses next to the fixed-pose baselines, in one run.

    python bench/pose_recovery.py SCENE [--views 4] [--rot 15] [--trans 0.1] [--preset quick] [key=value ...]

SCENE: a preset (maryrose, synthetic), a scene folder, or `synthetic-small` (16 views, 96 px, cached).
For the scene it trains three models with the same seed and schedule:
    bags        noisy poses, pose optimization on (the method)
    fixed-noisy noisy poses, frozen (GaussianObject, the baseline the report compares with)
    fixed-true  true poses, frozen (the upper bound)
and prints initial/final pose errors (Procrustes-aligned), held-out PSNR/SSIM (test cameras aligned, then 50
iterations of test-pose refinement with the Gaussians frozen) and seconds per iteration. `name=value` /
`group.name=value` pairs override TrainConfig fields (JSON values, as `warpbags train --set`), e.g.
`iters=900 rounds=3`; the repair stage is off unless `repair.iters` is given.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from warpbags.configs.train import load_preset, parse_settings
from warpbags.data import SyntheticOptions, ensure_synthetic_scene, load_scene, open_scene
from warpbags.evaluation import evaluate_run
from warpbags.trainer import Trainer, training_scene

VARIANTS = {
    "bags": dict(pose_opt=True),
    "fixed-noisy": dict(pose_opt=False),
    "fixed-true": dict(pose_opt=False, rot_noise_deg=0.0, trans_noise=0.0),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene")
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--rot", type=float, default=15.0, help="rotation noise std, degrees")
    parser.add_argument("--trans", type=float, default=0.1, help="camera-centre noise std (orbit radius 4)")
    parser.add_argument("--preset", default="quick")
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("overrides", nargs="*", help="TrainConfig fields as name=value or group.name=value (JSON values)")
    args = parser.parse_intermixed_args()
    torch.set_num_threads(1)
    overrides = parse_settings(args.overrides)
    if args.scene == "synthetic-small":
        scene = load_scene(ensure_synthetic_scene(SyntheticOptions(views=16, width=96, height=96)),
                           name="synthetic-small")
    else:
        scene = open_scene(args.scene)

    print(f"{args.scene}: {args.views} views, noise {args.rot} deg / {args.trans}, preset {args.preset} {overrides}")
    header = (f"{'variant':<12} {'rot init':>8} {'rot final':>9} {'trans init':>10} {'trans final':>11} "
              f"{'PSNR':>6} {'SSIM':>6} {'PSNR*':>6} {'s/iter':>7}")
    print(header + "\n" + "-" * len(header), flush=True)
    with tempfile.TemporaryDirectory() as root:
        for name in args.variants.split(","):
            settings = dict(views=args.views, rot_noise_deg=args.rot, trans_noise=args.trans, repair={"iters": 0})
            settings.update(overrides)
            settings.update(VARIANTS[name])
            config = load_preset(args.preset, **settings)
            out = Path(root) / name
            trainer = Trainer(training_scene(scene, config), config, out, log=lambda message: None)
            trainer.write_run_files()
            started = time.perf_counter()
            trainer.train()
            seconds = (time.perf_counter() - started) / config.total_iters
            report = evaluate_run(out, refine_iters=50, log=lambda message: None)
            poses = report["poses"]["procrustes"]
            aligned, refined = report["images"]["mean"], report["images_after_test_pose_refinement"]["mean"]
            print(f"{name:<12} {poses['initial']['rotation_deg_mean']:>8.3f} {poses['final']['rotation_deg_mean']:>9.3f} "
                  f"{poses['initial']['translation_mean']:>10.4f} {poses['final']['translation_mean']:>11.4f} "
                  f"{aligned['psnr']:>6.2f} {aligned['ssim']:>6.3f} {refined['psnr']:>6.2f} {seconds:>7.3f}",
                  flush=True)
    print("rotation in degrees, translation in scene units (orbit radius 4), after sim(3) Procrustes alignment;\n"
          "PSNR/SSIM on held-out views with aligned test poses, PSNR* after 50 test-pose refinement iterations.")


if __name__ == "__main__":
    main()
