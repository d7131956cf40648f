"""`warpbags eval RUN`: held-out image metrics and camera-pose accuracy of a run; `warpbags agree RUN RUN ...`: how
far several runs of one capture agree on its poses."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from warpbags.agreement import pose_agreement
from warpbags.cli.common import clean_errors, stdout
from warpbags.errors import WarpbagsError
from warpbags.evaluation import evaluate_run
from warpbags.files import atomic_output, finite_json, writable_folder
from warpbags.run_folder import latest_run, load_run


def _fmt(value, digits: int) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def evaluate(
    run_dir: Optional[Path] = typer.Argument(None, help="Run folder (default: the last finished under runs/)."),
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

    images = Table(title=f"held-out views ({result['test_views']}, {result['alignment']} alignment)",
                   title_justify="left")
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


def agree(
    run_dirs: list[Path] = typer.Argument(..., help="Two or more finished runs of one capture and the same views, "
                                          "started from the same poses (e.g. --seed 0, 1, 2; with injected noise, "
                                          "one --noise-seed)."),
    procrustes: bool = typer.Option(True, "--procrustes/--pairwise",
                                    help="Align each pair of runs by sim(3) Procrustes or SPARF's pairwise alignment."),
    json_path: Optional[Path] = typer.Option(None, "--json", help="Also write the comparison to this JSON file "
                                             "(outside the run folders: agree never changes a run)."),
) -> None:
    """How far runs of one capture agree on each camera's pose, with no reference poses needed: where runs that
    differ only in their seed end d degrees apart, the views do not determine that camera, and the runs' errors
    there add up to at least d."""
    if json_path is not None:
        if json_path.is_dir():
            raise WarpbagsError(f"--json {json_path} is a folder: name the file to write")
        writable_folder(json_path.parent, "to write --json into")
        target = json_path.resolve()
        for run_dir in run_dirs:  # agree reads runs and never changes one (config.json, eval.json, ...)
            if run_dir.resolve() in target.parents:
                raise WarpbagsError(f"--json {json_path} is inside the run folder {run_dir}: write it elsewhere, "
                                    "agree never changes a run")
    runs = [load_run(path) for path in run_dirs]
    result = pose_agreement(runs, "procrustes" if procrustes else "pairwise")

    title = (f"pose agreement of {len(runs)} runs ({len(result.image_names)} views, {result.alignment} alignment of "
             "each pair; over the pairs)")
    table = Table(title=title, title_justify="left")
    columns = ["camera", "image", "rot med", "rot max", "centre max", "px max"]
    for column in columns + (["error"] if result.error_deg is not None else []):
        table.add_column(column)
    summary = result.per_camera()
    for camera, name in enumerate(result.image_names):
        row = [str(camera), name, f"{summary['rotation_deg_median'][camera]:.2f}",
               f"{summary['rotation_deg_max'][camera]:.2f}", f"{summary['centre_percent_of_orbit_max'][camera]:.2f}",
               f"{summary['pixels_max'][camera]:.2f}" if "pixels_max" in summary else "n/a"]
        if result.error_deg is not None:
            row.append(f"{result.error_deg[:, camera].mean():.2f}")
        table.add_row(*row)
    stdout.print(table)
    stdout.print(f"runs disagree by {result.rotation_deg.mean():.2f} deg (mean over pairs and cameras); each run's "
                 "mean disagreement with the others: " + ", ".join(
                     f"{path} {value:.2f}" for path, value in zip(result.runs, result.run_disagreement_deg())))
    if result.central_run() is not None:
        stdout.print(f"closest to the others: {result.runs[result.central_run()]}")
    if not result.same_start:
        stdout.print("the runs started from different poses: their disagreement includes how far apart they started")
    stdout.print("rot: degrees between two runs' orientations of a camera; centre: % of the orbit radius; px: RMS "
                 "pixels the object moves between two runs' cameras" + (
                     "; error: against the scene's own poses, which the runs perturbed before training (degrees, mean "
                     "over the runs)" if result.error_deg is not None else ""))
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_output(json_path) as temporary:
            temporary.write_text(finite_json(result.to_json()))
        stdout.print(f"wrote {json_path}")


def register(app: typer.Typer) -> None:
    """Add `eval` and `agree` to `app`."""
    app.command("eval")(clean_errors(evaluate))
    app.command("agree")(clean_errors(agree))
