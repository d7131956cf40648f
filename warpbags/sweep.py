"""`warpbags sweep`: BAGS against the fixed-pose baseline over rotation noise, view counts and seeds.

Each combination is one run folder `<out>/<method>-<views>v-rot<noise>-seed<seed>/` (trained, then evaluated).
A folder that already holds eval.json is skipped and one with checkpoints is resumed, so an interrupted sweep
continues where it stopped. Results: `<out>/sweep.json`, `<out>/sweep.csv` and the plots of `warpbags.report`.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from warpbags.configs.train import load_preset
from warpbags.data import open_scene
from warpbags.errors import WarpbagsError
from warpbags.evaluation import evaluate_run
from warpbags.files import atomic_output
from warpbags.report import plot_sweep
from warpbags.trainer import start_or_resume, training_scene

METHODS = {"baseline": False, "bags": True}  # method -> pose optimization


@dataclass(frozen=True)
class SweepSpec:
    """What to sweep. `overrides` are TrainConfig fields applied to every run (e.g. iters)."""

    scene: str
    out: Path
    rot_noises: tuple[float, ...] = (0, 5, 10, 15, 20, 30)
    views: tuple[int, ...] = (4, 6, 9)
    seeds: tuple[int, ...] = (0,)
    trans_noise: float = 0.0
    preset: str = "quick"
    refine_iters: int = 50
    overrides: tuple[tuple[str, object], ...] = ()


def run_sweep(spec: SweepSpec, data_root: Path | None = None, log: Callable[[str], None] = print) -> list[dict]:
    """Train and evaluate every combination not done yet; returns one row per run."""
    if any(noise < 0 for noise in spec.rot_noises):
        raise WarpbagsError(f"--rot-noises must be >= 0, got {list(spec.rot_noises)}")
    if any(views < 2 for views in spec.views):
        raise WarpbagsError(f"--views must be >= 2, got {list(spec.views)}")
    scene = open_scene(spec.scene, root=data_root)
    spec.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for views in spec.views:
        for noise in spec.rot_noises:
            for seed in spec.seeds:
                for method, pose_opt in METHODS.items():
                    run_dir = spec.out / f"{method}-{views}v-rot{noise:g}-seed{seed}"
                    if (run_dir / "eval.json").is_file():
                        log(f"skip {run_dir.name} (done)")
                    else:
                        config = load_preset(spec.preset, views=views, rot_noise_deg=float(noise),
                                             trans_noise=spec.trans_noise, pose_opt=pose_opt, seed=seed,
                                             noise_seed=seed, **dict(spec.overrides))
                        resume = any((run_dir / "checkpoints").glob("checkpoint_*.pt"))
                        log(f"{'resume' if resume else 'train'} {run_dir.name}")
                        trainer = start_or_resume(training_scene(scene, config), config, run_dir, resume=resume,
                                                  log=lambda message: None)
                        trainer.train()
                        evaluate_run(run_dir, refine_iters=spec.refine_iters, log=lambda message: None)
                    rows.append(_row(run_dir, method, views, noise, seed))
    _write_tables(rows, spec.out)
    plot_sweep(rows, spec.out)
    return rows


def _row(run_dir: Path, method: str, views: int, noise: float, seed: int) -> dict:
    report = json.loads((run_dir / "eval.json").read_text())
    poses = report["poses"]["procrustes"]
    refined = report.get("images_after_test_pose_refinement", report["images"])
    return {
        "method": method, "views": views, "rot_noise_deg": noise, "seed": seed,
        "rot_err_initial": poses["initial"]["rotation_deg_mean"], "rot_err_final": poses["final"]["rotation_deg_mean"],
        "trans_err_initial": poses["initial"]["translation_mean"], "trans_err_final": poses["final"]["translation_mean"],
        "psnr": report["images"]["mean"]["psnr"], "ssim": report["images"]["mean"]["ssim"],
        "flip": report["images"]["mean"].get("flip"),
        "psnr_refined": refined["mean"]["psnr"], "run": run_dir.name,
    }


def _write_tables(rows: list[dict], out: Path) -> None:
    with atomic_output(out / "sweep.json") as temporary:
        temporary.write_text(json.dumps(rows, indent=2))
    with atomic_output(out / "sweep.csv") as temporary, open(temporary, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
