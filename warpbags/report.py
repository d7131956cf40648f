"""Pictures and a Markdown report for a run (next to its eval.json), and the plots of a sweep.

Plots use matplotlib's Agg backend (files only, no display). It is imported on first use: the trainer imports this
module (the repair stage writes image grids), and matplotlib costs it ~40 MB of memory and ~0.4 s of start-up.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from warpbags.files import atomic_output, write_image
from warpbags.run_folder import RunFolder


def _pyplot():
    """matplotlib.pyplot on the Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save_figure(plt, figure, path: Path) -> None:
    """`figure` as the PNG `path`, atomically (a kill mid-write leaves the earlier figure, not half a file)."""
    figure.tight_layout()
    with atomic_output(path) as temporary:
        figure.savefig(temporary, dpi=110, format="png")
    plt.close(figure)


def plot_training_curves(records: list[dict], path: Path, alignment: str) -> None:
    """Total loss and pose errors over iterations (the report's Figs. 6 and 7 for one run), the errors as training
    logged them, after `alignment`; a dotted line marks the start of the repair stage."""
    iters = [r["iter"] for r in records]
    plt = _pyplot()
    figure, (loss_axis, pose_axis) = plt.subplots(1, 2, figsize=(10, 3.6))
    loss_axis.plot(iters, [r["loss"] for r in records])
    loss_axis.set(xlabel="iteration", ylabel="total loss", yscale="log", title="loss")
    pose_axis.plot(iters, [r["rot_err_deg"] for r in records], label="rotation (deg)")
    twin = pose_axis.twinx()
    twin.plot(iters, [r["trans_err"] for r in records], color="tab:orange", label="translation")
    pose_axis.set(xlabel="iteration", ylabel="rotation error (deg)", title=f"pose error ({alignment} alignment)")
    twin.set_ylabel("translation error")
    repair = [r["iter"] for r in records if r.get("stage") == "repair"]
    if repair:  # where the repair stage starts
        for axis in (loss_axis, pose_axis):
            axis.axvline(repair[0], color="gray", linestyle=":", linewidth=1)
    _save_figure(plt, figure, path)


def image_strip(paths: list[Path], out: Path, height: int = 128) -> list[Path]:
    """The images of `paths` side by side, each scaled to `height` pixels, written to `out` (atomically; nothing
    when none can be read). Returns the paths that could not be read as images, which the strip leaves out."""
    images, unreadable = [], []
    for path in paths:
        image = cv2.imread(str(path)) if path.is_file() else None
        if image is None or image.size == 0:
            unreadable.append(path)
            continue
        images.append(cv2.resize(image, (max(1, round(image.shape[1] * height / image.shape[0])), height),
                                 interpolation=cv2.INTER_AREA))
    if images:
        with atomic_output(out) as temporary:
            write_image(temporary, np.concatenate(images, axis=1))
    return unreadable


def write_image_grid(path: Path, rows: list[list]) -> None:
    """A PNG of [H, W, 3] RGB images in [0, 1] (tensors or arrays, all the same size), row by row (atomically)."""
    grid = np.concatenate([np.concatenate([np.asarray(image, dtype=np.float32) for image in row], axis=1)
                           for row in rows], axis=0)
    pixels = (np.clip(grid, 0, 1) * 255 + 0.5).astype(np.uint8)
    with atomic_output(path) as temporary:
        write_image(temporary, cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR))


# What `write_run_report` writes into the run folder (curves.png with a log, the strip with turntable frames).
REPORT_FILES = ("report.md", "curves.png", "turntable_strip.png")


def write_run_report(run_dir: Path, result: dict, training_alignment: str, records: list[dict] | None = None) -> Path:
    """report.md: the metrics table, training curves (whose pose errors training logged after
    `training_alignment`), held-out comparisons and (if rendered) a turntable strip. `records`: the run's log
    (`RunFolder.read_log`), read here when not given (a caller that writes other files first reads it before)."""
    run_dir = Path(run_dir)
    records = RunFolder(run_dir).read_log() if records is None else records
    lines = [f"# {result['scene']}: {result['views']} views", "", f"Run folder: `{run_dir}`", ""]
    lines += ["## Camera poses (training views)", "",
              "| alignment | stage | rotation mean (deg) | rotation median (deg) | centre floor (deg) | translation mean "
              "| % of orbit | object motion (px) |",
              "|---|---|---|---|---|---|---|---|"]
    for name, entry in result["poses"].items():
        for stage in ("initial", "final"):
            e = entry[stage]
            floor, pixels = e.get("rotation_deg_centre_floor_mean"), e.get("reprojection_px_mean")
            lines.append(f"| {name} | {stage} | {e['rotation_deg_mean']:.3f} | {e['rotation_deg_median']:.3f} | "
                         f"{'n/a' if floor is None else f'{floor:.3f}'} | {e['translation_mean']:.4f} | "
                         f"{e['translation_percent_of_orbit']:.2f} | {'n/a' if pixels is None else f'{pixels:.2f}'} |")
    lines += ["", "Centre floor: the rotation error that the camera centres alone force on cameras that look at the "
              "object (Procrustes only). Object motion: how far the pose error moves the object in each image (RMS "
              "pixels at the training resolution over the trained Gaussians' opaque centres, mean over cameras)."]
    for name, entry in result["poses"].items():
        if entry.get("weakly_fixed"):
            lines += ["", f"{name.capitalize()}: {entry['weakly_fixed']}; the pairwise rows do not depend on it."]
    searches = [(r["iter"], r["view_hypotheses"]) for r in records if "view_hypotheses" in r]
    if searches:
        lines += ["", "## Turns of the worst-fit camera", "",
                  "| from iteration | camera | best turn | its loss | unturned loss | kept |", "|---|---|---|---|---|---|"]
        lines += [f"| {iteration - 1} | {s['camera']} | {s['best_turn']} | {s['best_loss']:.4f} | "
                  f"{s['unturned_loss']:.4f} | {'yes' if s['kept'] else 'no'} |" for iteration, s in searches]
    lines += ["", f"## Held-out views ({result['test_views']}, test cameras aligned by {result['alignment']})", "",
              "| test poses | PSNR | SSIM | FLIP | LPIPS |", "|---|---|---|---|---|"]
    rows = [("aligned", result["images"])]
    if "images_after_test_pose_refinement" in result:
        refined = result["images_after_test_pose_refinement"]
        rows.append((f"+ {refined['iters']} refinement iterations", refined))
    for label, metrics in rows:
        mean = metrics["mean"]
        flip, lpips = ("n/a" if mean.get(key) is None else f"{mean[key]:.4f}" for key in ("flip", "lpips"))
        lines.append(f"| {label} | {mean['psnr']:.2f} | {mean['ssim']:.4f} | {flip} | {lpips} |")
    lines += ["", "FLIP: NVIDIA's LDR-FLIP error at 67 pixels per degree, in [0, 1], lower is better."]
    for name in ("flip", "lpips"):
        if result.get(f"{name}_unavailable"):
            lines += ["", f"{name.upper()} unavailable: {result[f'{name}_unavailable']}"]
    if records:
        plot_training_curves(records, run_dir / "curves.png", training_alignment)
        lines += ["", "## Training", "", "![loss and pose error](curves.png)"]
    comparisons = sorted((run_dir / "eval").glob("*.png"))
    if comparisons:
        # the pictures show the last render eval made: the refined one where the test poses were refined
        refined = result.get("images_after_test_pose_refinement")
        render = "render" if refined is None else f"render after {refined['iters']} refinement iterations"
        lines += ["", f"## Held-out views: truth | {render} | 4x error", ""]
        lines += [f"![{path.stem}](eval/{path.name})" for path in comparisons]
    # in frame order: shorter names first, since an earlier warpbags padded to 3 digits (frame_999, frame_1000)
    frames = sorted((run_dir / "turntable").glob("frame_*.png"), key=lambda path: (len(path.name), path.name))
    if frames:
        picks = frames[:: max(1, len(frames) // 6)][:6]
        unreadable = image_strip(picks, run_dir / "turntable_strip.png")
        lines += ["", "## Novel views (turntable)", ""]
        if len(unreadable) < len(picks):
            lines += ["![turntable](turntable_strip.png)"]
        if unreadable:  # a frame damaged after `warpbags render` wrote it: the report goes on without it
            lines += ["", "Not readable as images, left out: " + ", ".join(f"`turntable/{path.name}`"
                                                                        for path in unreadable)]
    path = run_dir / "report.md"
    with atomic_output(path) as temporary:
        temporary.write_text("\n".join(lines) + "\n")
    return path


SWEEP_FIGURES = ("curves.png", "psnr_vs_noise.png", "pose_error_vs_noise.png")
"""What `plot_sweep` writes into a sweep's folder."""


def plot_sweep(rows: list[dict], out_dir: Path) -> list[Path]:
    """The report's figures for a sweep: PSNR against rotation noise for BAGS and the fixed-pose baseline (Fig. 5),
    final rotation error against noise, and per-run curves over iterations of the total loss (Fig. 6) and of the
    rotation error (Fig. 7), read from each run's log.jsonl."""
    written = []
    plt = _pyplot()
    figure, (loss_axis, pose_axis) = plt.subplots(1, 2, figsize=(11, 3.8))
    seeded = len({row["seed"] for row in rows}) > 1  # the seed tells apart curves of one method, views and noise
    for row in rows:
        records = RunFolder(out_dir / row["run"]).read_log()
        if not records:
            continue
        iters = [r["iter"] for r in records]
        label = f"{row['method']}, {row['views']}v, {row['rot_noise_deg']:g} deg"
        if seeded:
            label += f", seed {row['seed']}"
        style = "-" if row["method"] == "bags" else "--"
        loss_axis.plot(iters, [r["loss"] for r in records], style, label=label, linewidth=1)
        pose_axis.plot(iters, [r["rot_err_deg"] for r in records], style, label=label, linewidth=1)
    loss_axis.set(xlabel="iteration", ylabel="total loss", yscale="log", title="loss (Fig. 6)")
    pose_axis.set(xlabel="iteration", ylabel="rotation error (deg)", title="pose error (Fig. 7)")
    if pose_axis.lines:  # runs without a log (their rows read from eval.json alone) draw no curve to name
        pose_axis.legend(fontsize=7)
    _save_figure(plt, figure, out_dir / "curves.png")
    written.append(out_dir / "curves.png")
    for key, ylabel, name in (("psnr", "held-out PSNR (dB)", "psnr_vs_noise.png"),
                              ("rot_err_final", "final rotation error (deg)", "pose_error_vs_noise.png")):
        figure, axis = plt.subplots(figsize=(5.5, 3.8))
        for method, style in (("bags", "-o"), ("baseline", "--s")):
            for views in sorted({r["views"] for r in rows}):
                selected = [r for r in rows if r["method"] == method and r["views"] == views]
                noises, means = [], []
                for noise in sorted({r["rot_noise_deg"] for r in selected}):
                    # null (not finite in eval.json): left out of the mean; a noise level with none, off the line
                    values = [r[key] for r in selected if r["rot_noise_deg"] == noise and r[key] is not None]
                    if values:
                        noises.append(noise)
                        means.append(np.mean(values))
                axis.plot(noises, means, style, label=f"{method}, {views} views")
        axis.set(xlabel="rotation noise (deg)", ylabel=ylabel)
        axis.legend(fontsize=8)
        _save_figure(plt, figure, out_dir / name)
        written.append(out_dir / name)
    return written
