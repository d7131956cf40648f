"""What the repair stage buys: held-out image quality before vs after it, and what it costs, in one run.

    python bench/repair.py SCENE [SCENE ...] [--views 4] [--rot 0] [--trans 0] [--repair-iters 300]
                           [--preset quick] [--set name=value ...]

SCENE: as bench/pose_recovery.py (a preset such as maryrose or synthetic, a scene folder, or one of its small
synthetic scenes: `synthetic-small`, 16 views, 96 px, cached).
Per scene, one run trains the coarse stage, then the repair stage. Two controls continue the same coarse model
for the same number of iterations:
    real      the real views alone (pseudo-view ratio 0): what the pseudo views add over more iterations;
    identity  pseudo views whose targets are their own unrepaired renders: what the repairer adds.
All four models are evaluated the same way: held-out PSNR / SSIM / LPIPS (LPIPS only where the `lpips` package
and its weights are available) with the test cameras aligned by Procrustes, again after 50 iterations of
test-pose refinement (*), and the training-pose rotation error. Also printed: the PSNR of the coarse model's
held-out renders before and after the repairer (does it move novel views towards the truth?), the repairer's
L1 to the real images on its own training pairs (identity vs repaired), and the seconds spent in the coarse
stage, in building pairs and fitting the repairer, and in the repair iterations. `--set name=value` /
`--set group.name=value` overrides TrainConfig fields (JSON values, as `warpbags train --set`), e.g.
`--set seed=1 --set repair.fit_steps=800` (views, rot_noise_deg and trans_noise: --views, --rot and --trans).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from common import (add_training_options, check_options, merge_settings, open_bench_scene, pose_noise_checks,
                    training_overrides)
from warpbags.configs.train import load_preset
from warpbags.errors import WarpbagsError
from warpbags.evaluation import evaluate_run, held_out_views, psnr, test_cameras_in_model_frame
from warpbags.gaussians import render_gaussians, sh_degree_of
from warpbags.run_folder import load_run
from warpbags.trainer import Trainer, training_scene
from warpbags.cli.common import clean_errors


def _metrics(run_dir: Path) -> dict:
    report = evaluate_run(run_dir, refine_iters=50, log=lambda message: None)
    aligned, refined = report["images"]["mean"], report["images_after_test_pose_refinement"]["mean"]
    return {"psnr": aligned["psnr"], "ssim": aligned["ssim"], "lpips": aligned["lpips"], "psnr_refined": refined["psnr"],
            "ssim_refined": refined["ssim"], "rot": report["poses"]["procrustes"]["final"]["rotation_deg_mean"]}


class IdentityRepairer:
    """A repairer that changes nothing: pseudo views are then supervised by their own renders."""

    def fit(self, pairs, log) -> dict:
        return {}

    def repair(self, images: torch.Tensor) -> torch.Tensor:
        return images

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass


# What a control changes from the run whose coarse checkpoint it continues (the real views alone).
CONTROL_CHANGES = frozenset({"pseudo_ratio_start", "pseudo_ratio_end"})


def _continue(scene, config, checkpoint: Path, out: Path, repairer=None) -> tuple[Path, float]:
    """Train a copy of the checkpointed coarse model through `config`'s repair iterations; (run folder, seconds)."""
    trainer = Trainer(training_scene(scene, config), config, out, log=lambda message: None)
    trainer.write_run_files()
    trainer.load_checkpoint(checkpoint, changed_on_purpose=CONTROL_CHANGES)
    if repairer is not None:
        trainer.start_repair_stage(repairer)
    started = time.perf_counter()
    trainer.train()
    return out, time.perf_counter() - started


def _repairer_on_held_out(coarse_dir: Path, repairer) -> tuple[float, float]:
    """Mean held-out PSNR of the coarse model's renders (test cameras Procrustes-aligned) before and after the
    repairer: does the repairer move novel views of this scene towards the truth?"""
    run = load_run(coarse_dir)
    test = held_out_views(run)
    viewmats = test_cameras_in_model_frame(run, test, "procrustes")
    targets = test.on_background(1.0).double().numpy()
    with torch.no_grad():
        renders, _, _ = render_gaussians(run.params, viewmats, test.Ks, test.width, test.height,
                                         sh_degree=sh_degree_of(run.params), backgrounds=torch.ones(len(viewmats), 3))
    renders = renders.clamp(0, 1)

    def mean_psnr(images: torch.Tensor) -> float:
        return float(np.mean([psnr(image, target) for image, target in zip(images.double().numpy(), targets)]))

    return mean_psnr(renders), mean_psnr(repairer.repair(renders))


def _run_paths(root: Path, name: str, views: int) -> dict[str, Path]:
    """Where a scene's runs go under `root`: the repair run, the copy of its coarse checkpoint and the two controls."""
    return {"repair": root / f"{name}-{views}v-repair", "coarse": root / f"{name}-coarse.pt",
            "real": root / f"{name}-real-only", "identity": root / f"{name}-identity"}


def _fmt(value, digits: int) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--rot", type=float, default=0.0, help="rotation noise std, degrees")
    parser.add_argument("--trans", type=float, default=0.0, help="camera-centre noise std (orbit radius 4)")
    parser.add_argument("--repair-iters", type=int, default=300)
    parser.add_argument("--keep", type=Path, help="keep the run folders under this folder (to look at the samples)")
    # An option, not trailing positionals: those would be taken as more scenes.
    add_training_options(parser, "a TrainConfig field as name=value or group.name=value (JSON value) for every run "
                                 "(repeatable), as `warpbags train --set`")
    args = parser.parse_args()
    torch.set_num_threads(1)
    check_options(pose_noise_checks(args.rot, args.trans))
    overrides = training_overrides(args, fixed={"views": "from --views", "rot_noise_deg": "from --rot",
                                                "trans_noise": "from --trans"},
                                   runs=[(f"--views {args.views}", dict(views=args.views, rot_noise_deg=args.rot,
                                                                        trans_noise=args.trans))])
    repair_settings = overrides.pop("repair", {})
    repair = {"iters": args.repair_iters, **repair_settings}  # a repair.iters setting wins
    settings = merge_settings(overrides, dict(views=args.views, rot_noise_deg=args.rot, trans_noise=args.trans,
                                              repair=repair))
    load_preset(args.preset, **settings)  # a bad preset or setting fails before the first line
    if repair["iters"] < 1:  # else the runs would stop after the coarse stage, with no repair stage to measure
        source = "--set repair.iters" if "iters" in repair_settings else "--repair-iters"
        raise WarpbagsError(f"{source} must be >= 1 (this benchmark measures the repair stage), got {repair['iters']}")
    if args.keep is not None:  # a second run into the same folder would reuse the first's pairs and checkpoints
        for name in args.scenes:
            for path in _run_paths(args.keep, name, args.views).values():
                if path.exists():
                    raise WarpbagsError(f"--keep {args.keep}: {path} exists (an earlier run's); choose a new folder")
    scenes = {name: open_bench_scene(name) for name in args.scenes}  # a bad name fails before the first line
    print(f"{args.views} views, noise {args.rot} deg / {args.trans}, preset {args.preset}, repair {repair} {overrides}")
    header = (f"{'scene':<16} {'model':<8} {'PSNR':>6} {'SSIM':>6} {'LPIPS':>6} {'PSNR*':>6} {'SSIM*':>6} "
              f"{'rot':>6}")
    with tempfile.TemporaryDirectory() as scratch:
        root = args.keep or Path(scratch)
        for name, scene in scenes.items():
            config = load_preset(args.preset, **settings)
            paths = _run_paths(root, name, args.views)
            out = paths["repair"]
            trainer = Trainer(training_scene(scene, config), config, out, log=lambda message: None)
            trainer.write_run_files()
            started = time.perf_counter()
            trainer.train(stop_at=config.iters)
            coarse_seconds = time.perf_counter() - started

            coarse_checkpoint = paths["coarse"]  # the run keeps only its newest checkpoints
            shutil.copy(trainer.latest_checkpoint(), coarse_checkpoint)
            started = time.perf_counter()
            trainer.start_repair_stage()  # pairs + fit, timed on their own
            preparation_seconds = time.perf_counter() - started
            started = time.perf_counter()
            trainer.train()
            repair_seconds = time.perf_counter() - started
            # Controls from the same coarse model and the same number of iterations: the real views alone, and
            # pseudo views whose targets are the renders themselves (what the repairer adds over that).
            real_only = dataclasses.replace(config, repair=dataclasses.replace(
                config.repair, pseudo_ratio_start=0.0, pseudo_ratio_end=0.0))
            real_out, real_seconds = _continue(scene, real_only, coarse_checkpoint, paths["real"])
            identity_out, _ = _continue(scene, config, coarse_checkpoint, paths["identity"], IdentityRepairer())
            fit = json.loads((out / "repair" / "fit.json").read_text())
            print(header + "\n" + "-" * len(header))
            for model, folder in (("coarse", out / "coarse"), ("real", real_out), ("identity", identity_out),
                                  ("repair", out)):
                m = _metrics(folder)
                print(f"{name:<16} {model:<8} {m['psnr']:>6.2f} {m['ssim']:>6.3f} {_fmt(m['lpips'], 3):>6} "
                      f"{m['psnr_refined']:>6.2f} {m['ssim_refined']:>6.3f} {m['rot']:>6.3f}", flush=True)
            before, after = _repairer_on_held_out(out / "coarse", trainer.repair_stage.repairer)
            print(f"repairer on the coarse model's held-out renders: PSNR {before:.2f} -> {after:.2f}")
            print("repairer L1 on its pairs (identity -> repaired): "
                  + ", ".join(f"{kind} {fit['l1_identity'][kind]:.4f} -> {fit['l1_repaired'][kind]:.4f}"
                              for kind in sorted(fit["l1_identity"])))
            print(f"seconds: coarse {coarse_seconds:.0f} ({config.iters} its), pairs + fit {preparation_seconds:.0f}, "
                  f"repair {repair_seconds:.0f} ({config.repair.iters} its), real-only {real_seconds:.0f}\n",
                  flush=True)
    print("PSNR/SSIM/LPIPS on held-out views (object on white) with Procrustes-aligned test poses; * after 50\n"
          "iterations of test-pose refinement; rot: mean training-pose rotation error (deg) after alignment.")


if __name__ == "__main__":
    clean_errors(main)()  # a bad scene name or setting: one line and exit code 2, as the CLI
