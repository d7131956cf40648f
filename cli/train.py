"""`warpbags train SCENE`: joint Gaussian + pose optimization from sparse views (see `warpbags.trainer`)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Optional

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from warpbags.cli.common import clean_errors, stdout
from warpbags.cli.train_options import DATA_ROOT_HELP, resumed_config, train_config, with_train_options
from warpbags.configs.scenes import SCENES
from warpbags.configs.train import DEFAULT_PRESET
from warpbags.data.catalog import check_data_root
from warpbags.errors import WarpbagsError, sigterm_stops
from warpbags.files import writable_folder
from warpbags.run_folder import RunFolder
from warpbags.trainer import default_run_dir, saved_run_config, saved_run_scene, start_or_resume, training_scene


@with_train_options(after="preset")
def train(
    scene: Optional[str] = typer.Argument(
        None, help=f"Preset name ({', '.join(sorted(SCENES))}) or a scene folder; with --resume, the run's own "
                   "when left out.", show_default=False),
    *,
    preset: Optional[str] = typer.Option(
        None, "--preset", help="paper (the report's schedule) or quick (CPU-sized; the default)."),
    settings: Optional[list[str]] = typer.Option(
        None, "--set", help="Any TrainConfig field: name=value or group.name=value, JSON values (repeatable), e.g. "
        "--set repair.fit_steps=800 --set lr.pose=0.005. A field is given once: by its option or by --set."),
    device: str = typer.Option("cpu", "--device", help="cpu or cuda."),
    data_root: Optional[Path] = typer.Option(None, "--data-root", help=DATA_ROOT_HELP),
    out: Optional[Path] = typer.Option(None, "--out", help="Run folder (default runs/<scene>-<views>v-<time>)."),
    resume: bool = typer.Option(False, "--resume", help="Continue the run in --out from its last checkpoint."),
    log_every: int = typer.Option(50, "--log-every", help="Without a terminal (CI, a log file): one line every N iterations."),
    **config_options: Any,  # one per row of warpbags.cli.train_options.TRAIN_OPTIONS
) -> None:
    """Train Gaussians and per-camera pose deltas (coarse stage, then the repair stage if it has iterations); writes
    config, logs, checkpoints, PLY and poses to the run folder."""
    if log_every < 1:
        raise WarpbagsError(f"--log-every must be >= 1, got {log_every}")
    if resume and out is None:
        raise WarpbagsError("--resume needs --out (the run folder to continue)")
    if scene is None and not resume:
        raise WarpbagsError("give the scene to train: a preset name or a scene folder (`warpbags train --help`)")
    if out is not None:  # before the scene is read (a minute for a folder of photographs)
        writable_folder(out, "to train into")
        if not resume:  # a new run starts in a new or empty folder (start_or_resume checks it again)
            RunFolder(out).require_new()
    # A resumed run goes on with the config it was started with; options given again must agree with it.
    config = (resumed_config(saved_run_config(out), preset, config_options, settings or [],
                             RunFolder(out).read_info().get("resolution")) if resume else
              train_config(preset or DEFAULT_PRESET, config_options, settings or []))
    # SIGTERM (kill, a job scheduler) stops the start as Ctrl-C does, so that a new run's claim on its folder is
    # removed; training takes both signals itself from its first iteration on
    with sigterm_stops():
        scene_name = scene if scene is not None else saved_run_scene(out, data_root)
        check_data_root(scene_name, data_root)
        scene_data = training_scene(scene_name, config, data_root, log=stdout.print)
        out = out or default_run_dir(scene_data.name, config.views)
        trainer = start_or_resume(scene_data, config, out, device=device, resume=resume, log=stdout.print)
    initial = trainer.pose_error(trainer.viewmats_init)
    repair_note = (f" + {trainer.config.repair.iters} repair" if trainer.config.repair.iters else "")
    # Without injected noise the scene's poses are where training starts, not a truth: say what the numbers mean.
    noisy = trainer.config.injects_pose_noise
    start = (f"initial pose error {initial['rot_err_deg']:.3f} deg / {initial['trans_err']:.4f}" if noisy else
             "starting from the scene's own poses (no noise injected): rot and trans are how far the cameras move "
             "from them")
    stdout.print(f"{scene_data.name}: {config.views} views at {scene_data.width}x{scene_data.height}, "
                 f"{trainer.config.iters}{repair_note} iterations ({trainer.config.preset}); {start}")
    try:
        if stdout.is_terminal:
            last = _train_with_progress_bar(trainer)
        else:
            last = _train_with_log_lines(trainer, log_every)
    except KeyboardInterrupt:
        if trainer.latest_checkpoint() is None:  # a new run removed what it had written (Trainer.train)
            stdout.print(f"stopped at iteration {trainer.iteration}, before the first checkpoint: nothing was kept",
                         style="yellow")
        else:
            stdout.print(f"stopped at iteration {trainer.iteration}; checkpoint saved, continue with --resume --out "
                         f"{out}", style="yellow")
        raise
    final = trainer.pose_error()
    poses = (f"pose error {initial['rot_err_deg']:.3f} -> {final['rot_err_deg']:.3f} deg, {initial['trans_err']:.4f} -> "
             f"{final['trans_err']:.4f}" if noisy else
             f"cameras moved {final['rot_err_deg']:.3f} deg / {final['trans_err']:.4f} from the scene's poses")
    # a resumed run that had already finished trains nothing and has no loss to show
    trained = (f"loss {last['loss']:.4f}" if "loss" in last else
               f"the run had already finished its {trainer.config.total_iters} iterations, nothing trained")
    stdout.print(f"done: {trained}, {len(trainer.params['means'])} Gaussians, {poses}; wrote {out}")


def register(app: typer.Typer) -> None:
    """Add `train` to `app`."""
    app.command("train")(clean_errors(train))


def _status(record: dict) -> str:
    return (f"{record['stage']}  loss {record['loss']:.4f}  N {record['num_gaussians']}  "
            f"rot {record['rot_err_deg']:.3f} deg  trans {record['trans_err']:.4f}")


def _train_with_progress_bar(trainer) -> dict:
    columns = [TextColumn("[bold]train"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[status]}"),
               TimeElapsedColumn(), TimeRemainingColumn()]
    # in training steps, the turn search's trial rounds included (`Trainer.steps_left`), so that the bar's rate and
    # time left hold through the search, whose trial steps move it too
    total = trainer.iteration + trainer.steps_left()
    with Progress(*columns, console=stdout, transient=False) as progress:
        task = progress.add_task("train", total=total, completed=trainer.iteration, status="")
        return trainer.train(callback=lambda record: progress.update(task, completed=total - trainer.steps_left(),
                                                                     status=_status(record)),
                             on_trial_step=lambda done: progress.update(task, completed=done, status="turn search"))


def _train_with_log_lines(trainer, every: int) -> dict:
    """One compact line every `every` iterations and at the end: what a log file or CI can read (no bar). The time
    per step and the time left count the turn search's trial rounds as steps (`Trainer.steps_left`), and the search
    prints a line every `every` of its trial steps, which are logged only once it ends."""
    total, started, first = trainer.config.total_iters, time.perf_counter(), trainer.iteration
    all_steps = first + trainer.steps_left()

    def seconds_per_step(done: int) -> float:
        return (time.perf_counter() - started) / max(done - first, 1)

    def line(record: dict) -> None:
        if record["iter"] % every and record["iter"] != total:
            return
        left = trainer.steps_left()
        per_step = seconds_per_step(all_steps - left)
        print(f"iter {record['iter']}/{total}  {_status(record)}  {per_step:.3f} s/step  eta {per_step * left:.0f} s",
              flush=True)

    def trial_line(done: int) -> None:
        if done % every:
            return
        per_step = seconds_per_step(done)
        print(f"turn search: step {done}/{all_steps}  {per_step:.3f} s/step  eta {per_step * (all_steps - done):.0f} s",
              flush=True)

    return trainer.train(callback=line, on_trial_step=trial_line)
