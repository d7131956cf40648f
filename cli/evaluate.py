"""`warpbags eval RUN`: held-out image metrics and camera-pose accuracy of a run."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from warpbags.cli.common import clean_errors
from warpbags.evaluation import evaluate_run
from warpbags.run_folder import latest_run

stdout = Console(highlight=False)


def _fmt(value, digits: int) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def evaluate(
    run_dir: Optional[Path] = typer.Argument(None, help="Run folder (default: the newest under runs/)."),
    procrustes: bool = typer.Option(
        True, "--procrustes/--pairwise",
        help="Map test cameras into the model's frame with sim(3) Procrustes (BARF) or SPARF's pairwise alignment.",
    ),
    refine_iters: int = typer.Option(
        100, "--refine-iters", help="Test-time pose refinement: L-BFGS iterations per held-out view (0 = off)."),
    device: str = typer.Option("cpu", "--device", help="cpu or cuda: where held-out views are rendered and refined."),
) -> None:
    """Render held-out views, compare with ground truth (PSNR/SSIM/FLIP/LPIPS) and measure camera-pose errors."""
    run_dir = run_dir or latest_run()
    alignment = "procrustes" if procrustes else "pairwise"
    result = evaluate_run(run_dir, alignment=alignment, refine_iters=refine_iters, device=device,
                          log=stdout.print)

    title = (f"training-camera pose error ({result['views']} views)" if result["pose_noise_injected"] else
             f"training cameras against the scene's own poses ({result['views']} views; no noise was injected, so "
             "the final rows are how far training moved them)")
    poses = Table(title=title, title_justify="left")
    for column in ("alignment", "stage", "rot mean", "rot median", "centre floor", "trans mean", "% orbit", "px"):
        poses.add_column(column, no_wrap=column in ("alignment", "stage"))
    for name, entry in result["poses"].items():
        for stage in ("initial", "final"):
            e = entry[stage]
            poses.add_row(name, stage, f"{e['rotation_deg_mean']:.3f}", f"{e['rotation_deg_median']:.3f}",
                          _fmt(e.get("rotation_deg_centre_floor_mean"), 3), f"{e['translation_mean']:.4f}",
                          f"{e['translation_percent_of_orbit']:.2f}", _fmt(e.get("reprojection_px_mean"), 2))
    stdout.print(poses)
    stdout.print("rotations in degrees; centre floor: the rotation error that the camera centres alone force on "
                 "cameras that look at the object; px: how far the pose error moves the object in each image (RMS "
                 "pixels at the training resolution, mean over cameras)")

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
    run = Path(result["run"])
    curves = " and curves.png" if (run / "curves.png").is_file() else ""
    stdout.print(f"wrote {run / 'eval.json'}, {run / 'eval'}/ and {run / 'report.md'}{curves}")


def register(app: typer.Typer) -> None:
    """Add `eval` to `app`."""
    app.command("eval")(clean_errors(evaluate))
