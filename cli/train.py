"""`warpbags train SCENE`: joint Gaussian + pose optimization from sparse views (see `warpbags.trainer`)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from warpbags.cli.common import clean_errors
from warpbags.configs.train import load_preset, parse_settings
from warpbags.errors import WarpbagsError
from warpbags.trainer import default_run_dir, start_or_resume, training_scene

stdout = Console(highlight=False)


def train(
    scene: str = typer.Argument(..., help="Preset name (kitchen, maryrose, synthetic) or a scene folder."),
    views: int = typer.Option(4, "--views", help="Training views, >= 2: the scene's sparse_N split, else a farthest-point choice."),
    preset: str = typer.Option("quick", "--preset", help="paper (the report's schedule) or quick (CPU-sized)."),
    iters: Optional[int] = typer.Option(None, "--iters", help="Coarse-stage iterations (default: the preset's)."),
    rounds: Optional[int] = typer.Option(None, "--rounds", help="Re-initialization rounds (default: the preset's)."),
    init: Optional[str] = typer.Option(None, "--init", help="Initial Gaussians: hull, sfm or random."),
    depth_loss: Optional[str] = typer.Option(None, "--depth-loss", help="Depth prior: mad (default) or pearson."),
    blur_px: Optional[float] = typer.Option(None, "--blur-px", help="Coarse-to-fine: initial blur sigma in pixels."),
    blur_until: Optional[int] = typer.Option(None, "--blur-until", help="Coarse-to-fine: round iteration where blur ends."),
    pose_opt_start: Optional[int] = typer.Option(None, "--pose-opt-start", help="First iteration with pose updates."),
    rot_noise_deg: float = typer.Option(0.0, "--rot-noise-deg", help="Injected rotation noise, std in degrees."),
    trans_noise: float = typer.Option(0.0, "--trans-noise", help="Injected camera-centre noise, std (orbit radius 4)."),
    no_pose_opt: bool = typer.Option(False, "--no-pose-opt", help="Keep poses fixed (GaussianObject baseline)."),
    fix_first_camera: bool = typer.Option(False, "--fix-first-camera", help="Keep camera 0 at its given pose as the gauge (default: every camera is optimized; errors after sim(3) alignment)."),
    camera_param: Optional[str] = typer.Option(None, "--camera-param", help="Pose parameterization: object (default; rotation about the object centre, CamP) or camera (se(3) about the camera centre)."),
    repair_iters: Optional[int] = typer.Option(None, "--repair-iters", help="Repair-stage iterations after the coarse stage (default: the preset's)."),
    no_repair: bool = typer.Option(False, "--no-repair", help="Skip the repair stage."),
    repairer: Optional[str] = typer.Option(None, "--repairer", help="unet (default) or package.module:factory."),
    seed: int = typer.Option(0, "--seed", help="Seed for initialization, view order and (unless --noise-seed) noise."),
    noise_seed: Optional[int] = typer.Option(None, "--noise-seed", help="Seed for the injected pose noise."),
    device: str = typer.Option("cpu", "--device", help="cpu or cuda."),
    resolution: Optional[int] = typer.Option(None, "--resolution", "-r", help="Load images_R (1, 2, 4, 8)."),
    max_image_size: Optional[int] = typer.Option(None, "--max-image-size", help="Downscale so the longer side is <= this (0 = off)."),
    data_root: Optional[Path] = typer.Option(None, "--data-root", help="Folder holding datasets."),
    out: Optional[Path] = typer.Option(None, "--out", help="Run folder (default runs/<scene>-<views>v-<time>)."),
    resume: bool = typer.Option(False, "--resume", help="Continue the run in --out from its last checkpoint."),
    log_every: int = typer.Option(50, "--log-every", help="Without a terminal (CI, a log file): one line every N iterations."),
    settings: Optional[list[str]] = typer.Option(
        None, "--set", help="Any TrainConfig field: name=value or group.name=value, JSON values (repeatable), e.g. "
        "--set repair.fit_steps=800 --set lr.pose=0.005."),
) -> None:
    """Train Gaussians and per-camera pose deltas (coarse stage, then the repair stage if it has iterations); writes
    config, logs, checkpoints, PLY and poses to the run folder."""
    if views < 2:
        raise WarpbagsError(f"--views must be >= 2, got {views}")
    if log_every < 1:
        raise WarpbagsError(f"--log-every must be >= 1, got {log_every}")
    if resume and out is None:
        raise WarpbagsError("--resume needs --out (the run folder to continue)")
    if no_repair and repair_iters:
        raise WarpbagsError("--no-repair and --repair-iters contradict each other; give one")
    options = dict(
        views=views, iters=iters, rounds=rounds, init=init, depth_loss=depth_loss, blur_sigma_px=blur_px,
        blur_until=blur_until, pose_opt_start=pose_opt_start, rot_noise_deg=rot_noise_deg, trans_noise=trans_noise,
        pose_opt=not no_pose_opt, seed=seed,
        noise_seed=seed if noise_seed is None else noise_seed, resolution=resolution, max_image_size=max_image_size,
    )
    overrides = parse_settings(settings or [])
    clash = sorted(set(overrides) & set(options))
    if clash:
        raise WarpbagsError(f"--set {clash[0]}: it has its own option, use that")
    repair = {"iters": 0 if no_repair else repair_iters, "repairer": repairer}
    repair = {key: value for key, value in repair.items() if value is not None}
    clash = sorted(set(overrides.get("repair", {})) & set(repair))
    if clash:
        raise WarpbagsError(f"--set repair.{clash[0]}: it has its own option, use that")
    camera = {"fix_first_camera": fix_first_camera or None, "parameterization": camera_param}
    camera = {key: value for key, value in camera.items() if value is not None}
    clash = sorted(set(overrides.get("camera", {})) & set(camera))
    if clash:
        raise WarpbagsError(f"--set camera.{clash[0]}: it has its own option, use that")
    if camera:
        overrides["camera"] = {**overrides.get("camera", {}), **camera}
    if repair:
        overrides["repair"] = {**overrides.get("repair", {}), **repair}
    config = load_preset(preset, **options, **overrides)
    scene_data = training_scene(scene, config, data_root, log=stdout.print)
    out = out or default_run_dir(scene_data.name, views)
    trainer = start_or_resume(scene_data, config, out, device=device, resume=resume, log=stdout.print)
    initial = trainer.pose_error(trainer.viewmats_init)
    repair_note = (f" + {trainer.config.repair.iters} repair" if trainer.config.repair.iters else "")
    stdout.print(
        f"{scene_data.name}: {views} views at {scene_data.width}x{scene_data.height}, {trainer.config.iters}{repair_note} "
        f"iterations ({trainer.config.preset}); initial pose error {initial['rot_err_deg']:.3f} deg / {initial['trans_err']:.4f}"
    )
    try:
        if stdout.is_terminal:
            last = _train_with_progress_bar(trainer)
        else:
            last = _train_with_log_lines(trainer, log_every)
    except KeyboardInterrupt:
        stdout.print(f"[yellow]stopped at iteration {trainer.iteration}; checkpoint saved, continue with "
                     f"--resume --out {out}[/]")
        raise
    final = trainer.pose_error()
    stdout.print(
        f"done: loss {last.get('loss', float('nan')):.4f}, {len(trainer.params['means'])} Gaussians, pose error "
        f"{initial['rot_err_deg']:.3f} -> {final['rot_err_deg']:.3f} deg, {initial['trans_err']:.4f} -> "
        f"{final['trans_err']:.4f}; wrote {out}"
    )


def register(app: typer.Typer) -> None:
    """Add `train` to `app`."""
    app.command("train")(clean_errors(train))


def _status(record: dict) -> str:
    return (f"{record['stage']}  loss {record['loss']:.4f}  N {record['num_gaussians']}  "
            f"rot {record['rot_err_deg']:.3f} deg  trans {record['trans_err']:.4f}")


def _train_with_progress_bar(trainer) -> dict:
    columns = [TextColumn("[bold]train"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[status]}"),
               TimeElapsedColumn(), TimeRemainingColumn()]
    with Progress(*columns, console=stdout, transient=False) as progress:
        task = progress.add_task("train", total=trainer.config.total_iters, completed=trainer.iteration, status="")
        return trainer.train(callback=lambda record: progress.update(task, completed=record["iter"],
                                                                     status=_status(record)))


def _train_with_log_lines(trainer, every: int) -> dict:
    """One compact line every `every` iterations and at the end: what a log file or CI can read (no bar)."""
    total, started, first = trainer.config.total_iters, time.perf_counter(), trainer.iteration

    def line(record: dict) -> None:
        if record["iter"] % every and record["iter"] != total:
            return
        per_iter = (time.perf_counter() - started) / max(record["iter"] - first, 1)
        eta = per_iter * (total - record["iter"])
        print(f"iter {record['iter']}/{total}  {_status(record)}  {per_iter:.3f} s/it  eta {eta:.0f} s", flush=True)

    return trainer.train(callback=line)
