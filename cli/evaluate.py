"""`warpbags eval`, `render`, `export` and `sweep`: metrics, pose accuracy, novel views, export, experiments."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from warpbags.cli.main import app, clean_errors
from warpbags.errors import WarpbagsError
from warpbags.evaluation import evaluate_run, export_run, latest_run, render_turntable
from warpbags.sweep import RAY_INSTALL, SweepSpec, make_executor, run_sweep

stdout = Console(highlight=False)


def _fmt(value, digits: int) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


@app.command("eval")
@clean_errors
def evaluate(
    run_dir: Optional[Path] = typer.Argument(None, help="Run folder (default: the newest under runs/)."),
    procrustes: bool = typer.Option(
        True, "--procrustes/--pairwise",
        help="Map test cameras into the model's frame with sim(3) Procrustes (BARF) or SPARF's pairwise alignment.",
    ),
    refine_iters: int = typer.Option(100, "--refine-iters", help="Test-time pose refinement iterations (0 = off)."),
) -> None:
    """Render held-out views, compare with ground truth (PSNR/SSIM/FLIP/LPIPS) and measure camera-pose errors."""
    run_dir = run_dir or latest_run()
    alignment = "procrustes" if procrustes else "pairwise"
    result = evaluate_run(run_dir, alignment=alignment, refine_iters=refine_iters, log=stdout.print)

    poses = Table(title=f"training-camera pose error ({result['views']} views)", title_justify="left")
    for column in ("alignment", "stage", "rotation mean (deg)", "rotation median", "translation mean",
                   "% of orbit"):
        poses.add_column(column)
    for name, entry in result["poses"].items():
        for stage in ("initial", "final"):
            e = entry[stage]
            poses.add_row(name, stage, f"{e['rotation_deg_mean']:.3f}", f"{e['rotation_deg_median']:.3f}",
                          f"{e['translation_mean']:.4f}", f"{e['translation_percent_of_orbit']:.2f}")
    stdout.print(poses)

    images = Table(title=f"held-out views ({result['test_views']}, {alignment} alignment)", title_justify="left")
    for column in ("test poses", "PSNR", "SSIM", "FLIP", "LPIPS"):
        images.add_column(column)
    rows = [("aligned", result["images"])]
    if "images_after_test_pose_refinement" in result:
        rows.append((f"+ {refine_iters} refinement its", result["images_after_test_pose_refinement"]))
    for label, metrics in rows:
        mean = metrics["mean"]
        images.add_row(label, _fmt(mean["psnr"], 2), _fmt(mean["ssim"], 4), _fmt(mean.get("flip"), 4),
                       _fmt(mean["lpips"], 4))
    stdout.print(images)
    stdout.print(f"wrote {Path(result['run']) / 'eval.json'} and {Path(result['run']) / 'eval'}/")


@app.command("export")
@clean_errors
def export(
    run_dir: Optional[Path] = typer.Argument(None, help="Run folder (default: the newest under runs/)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Output folder (default: RUN_DIR/export)."),
) -> None:
    """Write the Gaussians (standard 3DGS PLY) and final poses in the input scene's frame."""
    folder = export_run(run_dir or latest_run(), out)
    stdout.print(f"wrote {folder / 'gaussians.ply'} and {folder / 'poses_final.npy'} (input scene frame)")


@app.command("render")
@clean_errors
def render(
    run_dir: Optional[Path] = typer.Argument(None, help="Run folder (default: the newest under runs/)."),
    frames: int = typer.Option(36, "--frames", help="Views on the orbit."),
    video: bool = typer.Option(True, "--video/--no-video", help="Also write RUN_DIR/turntable.mp4."),
) -> None:
    """Render a turntable of novel views around the object (PNG frames, and an MP4 through OpenCV)."""
    folder = render_turntable(run_dir or latest_run(), frames=frames, video=video)
    stdout.print(f"wrote {frames} frames to {folder}" + (f" and {folder.parent / 'turntable.mp4'}" if video else ""))


def _numbers(text: str, kind=float) -> tuple:
    try:
        return tuple(kind(item) for item in text.split(",") if item.strip())
    except ValueError:
        raise WarpbagsError(f"expected comma-separated numbers, got {text!r}") from None


@app.command("sweep")
@clean_errors
def sweep(
    scene: str = typer.Argument(..., help="Preset name or scene folder."),
    rot_noises: str = typer.Option("0,5,10,15,20,30", "--rot-noises", help="Rotation noise levels (deg std)."),
    views: str = typer.Option("4,6,9", "--views", help="View counts."),
    seeds: str = typer.Option("0", "--seeds", help="Seeds (noise and initialization)."),
    trans_noise: float = typer.Option(0.0, "--trans-noise", help="Camera-centre noise std for every run."),
    preset: str = typer.Option("quick", "--preset", help="Training preset for every run."),
    iters: Optional[int] = typer.Option(None, "--iters", help="Coarse iterations per run (default: the preset's)."),
    repair_iters: Optional[int] = typer.Option(None, "--repair-iters", help="Repair iterations per run (default: the preset's)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Sweep folder (default runs/sweep-<scene>)."),
    data_root: Optional[Path] = typer.Option(None, "--data-root", help="Folder holding datasets."),
    device: str = typer.Option("cpu", "--device", help="cpu or cuda, for every run."),
    executor: str = typer.Option(
        "local", "--executor",
        help="local: one run after another in this process. ray: each run a Ray task, on a local Ray instance or "
             "the cluster at --address; the sweep folder must be on a filesystem every Ray node shares "
             f"({escape(RAY_INSTALL)}).",
    ),
    address: Optional[str] = typer.Option(
        None, "--address", help="Ray cluster to run on: HOST:6379, ray://HOST:10001, or auto for one started with "
                                "`ray start` on this machine (default: a local Ray instance for this sweep)."),
    cpus_per_run: Optional[int] = typer.Option(None, "--cpus-per-run", help="Ray: CPUs each run declares, and its CPU "
                                               "render threads (default: this machine's cores; 1 with --device cuda)."),
    gpus_per_run: Optional[float] = typer.Option(None, "--gpus-per-run", help="Ray: GPUs each run declares "
                                                 "(default: 1 with --device cuda, else 0)."),
) -> None:
    """BAGS vs the fixed-pose baseline over noise, views and seeds; resumable; sweep.csv/json and plots."""
    sweep_executor = make_executor(executor, address=address, cpus_per_run=cpus_per_run,
                                   gpus_per_run=gpus_per_run, device=device)
    overrides = {"iters": iters, "repair": None if repair_iters is None else {"iters": repair_iters}}
    overrides = tuple((key, value) for key, value in overrides.items() if value is not None)
    spec = SweepSpec(scene=scene, out=out or Path("runs") / f"sweep-{Path(scene).name}",
                     rot_noises=_numbers(rot_noises), views=_numbers(views, int), seeds=_numbers(seeds, int),
                     trans_noise=trans_noise, preset=preset, overrides=overrides, device=device)
    rows = run_sweep(spec, data_root=data_root, log=stdout.print, executor=sweep_executor)
    table = Table(title=f"sweep {scene}", title_justify="left")
    for column in ("method", "views", "noise", "seed", "rot init", "rot final", "PSNR", "PSNR refined"):
        table.add_column(column)
    for r in rows:
        table.add_row(r["method"], str(r["views"]), f"{r['rot_noise_deg']:g}", str(r["seed"]),
                      f"{r['rot_err_initial']:.2f}", f"{r['rot_err_final']:.2f}", f"{r['psnr']:.2f}",
                      f"{r['psnr_refined']:.2f}")
    stdout.print(table)
    stdout.print(f"wrote {spec.out / 'sweep.csv'}, {spec.out / 'sweep.json'} and plots in {spec.out}")
