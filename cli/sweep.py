"""`warpbags sweep SCENE`: BAGS against the fixed-pose baseline over noise levels, view counts and seeds."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape
from rich.table import Table

from warpbags.cli.common import clean_errors, parse_numbers, stdout
from warpbags.cli.train_options import DATA_ROOT_HELP, config_overrides
from warpbags.configs.train import DEFAULT_PRESET, SEEDS_END
from warpbags.errors import WarpbagsError, sigterm_stops
from warpbags.sweep import RAY_INSTALL, SweepSpec, make_executor, run_sweep


def sweep(
    scene: str = typer.Argument(..., help="Preset name or scene folder."),
    rot_noises: str = typer.Option("0,5,10,15,20,30", "--rot-noises", help="Rotation noise levels (deg std)."),
    views: str = typer.Option("4,6,9", "--views", help="View counts."),
    seeds: str = typer.Option("0", "--seeds", help="Seeds (noise and initialization), each in [0, 2^32)."),
    trans_noise: float = typer.Option(0.0, "--trans-noise", help="Camera-centre noise std for every run."),
    preset: str = typer.Option(DEFAULT_PRESET, "--preset", help="Training preset for every run."),
    iters: Optional[int] = typer.Option(None, "--iters", help="Coarse iterations per run (default: the preset's)."),
    repair_iters: Optional[int] = typer.Option(None, "--repair-iters", help="Repair iterations per run (default: the preset's)."),
    refine_iters: int = typer.Option(50, "--refine-iters", help="Test-pose refinement iterations of each run's "
                                     "evaluation (its PSNR refined; 0: none)."),
    settings: Optional[list[str]] = typer.Option(
        None, "--set", help="Any TrainConfig field for every run: name=value or group.name=value, JSON values "
        "(repeatable), e.g. --set lr.pose=0.005; not the fields the sweep sets per run (views, noise, seeds, "
        "pose_opt)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Sweep folder (default runs/sweep-<scene>)."),
    data_root: Optional[Path] = typer.Option(None, "--data-root", help=DATA_ROOT_HELP),
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
    overrides = tuple(sweep_overrides(iters, repair_iters, settings or [], executor).items())
    if refine_iters < 0:
        raise WarpbagsError(f"--refine-iters must be >= 0, got {refine_iters}")
    spec = SweepSpec(scene=scene, out=out or Path("runs") / f"sweep-{Path(scene).name}", refine_iters=refine_iters,
                     rot_noises=tuple(parse_numbers(rot_noises, "--rot-noises", minimum=0, maximum=180)),
                     views=tuple(parse_numbers(views, "--views", int, minimum=2)),  # a visual hull needs two
                     seeds=tuple(parse_numbers(seeds, "--seeds", int, minimum=0, maximum=SEEDS_END - 1)),
                     trans_noise=trans_noise, preset=preset, overrides=overrides, device=device)
    # SIGTERM (kill, a job scheduler) stops the sweep as Ctrl-C does, between runs too: its lock and a run's
    # unfinished start are removed; each run's training takes it itself (a checkpoint saved)
    with sigterm_stops():
        rows = run_sweep(spec, data_root=data_root, log=stdout.print, executor=sweep_executor)
    table = Table(title=f"sweep {scene}", title_justify="left")
    for column in ("method", "views", "noise", "seed", "rot init", "rot final", "PSNR", "PSNR refined"):
        table.add_column(column)
    for r in rows:
        table.add_row(r["method"], str(r["views"]), f"{r['rot_noise_deg']:g}", str(r["seed"]),
                      *(_shown(r[key]) for key in ("rot_err_initial", "rot_err_final", "psnr", "psnr_refined")))
    stdout.print(table)
    stdout.print(f"wrote {spec.out / 'sweep.csv'}, {spec.out / 'sweep.json'} and plots in {spec.out}")


# TrainConfig fields a sweep sets per run (or per Ray task), and the sweep option that gives them
_SET_BY_THE_SWEEP = {"views": "--views", "rot_noise_deg": "--rot-noises", "trans_noise": "--trans-noise",
                     "seed": "--seeds", "noise_seed": "--seeds", "pose_opt": "the sweep's two methods"}


def sweep_overrides(iters: int | None, repair_iters: int | None, settings: list[str], executor: str) -> dict:
    """The TrainConfig overrides every run of the sweep takes: --iters, --repair-iters and the `--set` items.

    Raises:
        WarpbagsError: a field given twice (--iters and --set iters=...), a `--set` of a field the sweep sets per
            run, or of render_threads with the Ray executor (its tasks render on --cpus-per-run threads).
    """
    overrides = config_overrides({"iters": iters, "repair_iters": repair_iters}, settings)
    for field, option in _SET_BY_THE_SWEEP.items():
        if field in overrides:
            raise WarpbagsError(f"--set {field}: a sweep sets it per run, by {option}")
    if executor == "ray" and "render_threads" in overrides:
        raise WarpbagsError("--set render_threads: a Ray sweep's runs render on --cpus-per-run threads")
    return overrides


def _shown(value: float | None) -> str:
    """A metric of the table, or n/a where eval.json holds null (not finite: the PSNR of an exact render)."""
    return "n/a" if value is None else f"{value:.2f}"


def register(app: typer.Typer) -> None:
    """Add `sweep` to `app`."""
    app.command("sweep")(clean_errors(sweep))
