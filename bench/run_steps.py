"""Whole training steps of a real run, timed: `Trainer.train_step` from the newest checkpoint of a run folder.

    python bench/run_steps.py RUN [--steps 20] [--warmup 5] [--iteration N]

`bench/train_step.py` times a fixed problem; this times the step a run really takes at its checkpoint, with its
Gaussian count, SH degree, loss terms (silhouette chamfer, mask, depth), densification bookkeeping and pose
updates, e.g. the paper preset's late steps at ~100k Gaussians. The run folder is copied first (resuming cuts its
log back to the checkpoint). Steps start at the checkpoint's iteration, or at `--iteration` (the Gaussians stay the
checkpoint's; use it for a finished run, whose schedule has no steps left).

Printed: Gaussians, SH degree, wall and CPU ms per step (medians), the cores used (CPU / wall), peak RSS, and the
Warp CPU launches run on the calling thread, by kernel: the serial part of a step (the rasterizer's launches run on
its own host threads and are not listed).
"""

from __future__ import annotations

import argparse
import collections
import resource
import shutil
import statistics
import tempfile
import threading
import time
from pathlib import Path

import torch

from warpbags.devices import init_warp_quietly

init_warp_quietly()  # the table, not Warp's banner and module loads, as the CLI

from warpbags.cli.common import clean_errors  # noqa: E402
from warpbags.data import load_scene  # noqa: E402
from warpbags.errors import WarpbagsError  # noqa: E402
from warpbags.run_folder import RunFolder  # noqa: E402
from warpbags.trainer import start_or_resume, training_scene  # noqa: E402


def _warp_cpu_launch():
    """The module holding Warp's CPU launch function, `warp._src.context.invoke(kernel, hooks, params, adjoint)`:
    private, since Warp has no public hook for timing launches.

    Raises:
        WarpbagsError: this Warp version has no such function (moved or renamed), checked before any work.
    """
    import inspect  # noqa: PLC0415

    import warp  # noqa: PLC0415

    try:
        import warp._src.context as context  # noqa: PLC0415 - private: see the docstring

        parameters = list(inspect.signature(context.invoke).parameters)
    except (ImportError, AttributeError, TypeError, ValueError):
        parameters = None
    if parameters != ["kernel", "hooks", "params", "adjoint"]:
        raise WarpbagsError(f"Warp {warp.__version__} has no warp._src.context.invoke(kernel, hooks, params, adjoint), "
                            "the CPU launch function this bench wraps to time launches: update _serial_launch_timer")
    return context


def _serial_launch_timer(context) -> tuple[dict, collections.Counter]:
    """Time Warp CPU launches made on the main thread, per (kernel, adjoint), by wrapping `context.invoke`
    (`context`: `_warp_cpu_launch()`)."""
    totals: dict = collections.defaultdict(float)
    counts: collections.Counter = collections.Counter()
    launch = context.invoke
    main = threading.main_thread()

    def timed(kernel, hooks, params, adjoint):
        started = time.perf_counter()
        launch(kernel, hooks, params, adjoint)
        if threading.current_thread() is main:
            totals[(kernel.key, adjoint)] += time.perf_counter() - started
            counts[(kernel.key, adjoint)] += 1

    context.invoke = timed
    return totals, counts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a run folder with checkpoints (warpbags train --out RUN)")
    parser.add_argument("--steps", type=int, default=20, help="timed steps")
    parser.add_argument("--warmup", type=int, default=5, help="untimed steps first")
    parser.add_argument("--iteration", type=int, default=None, help="start here instead of the checkpoint's")
    args = parser.parse_args()
    if args.steps < 1 or args.warmup < 0:
        raise WarpbagsError(f"--steps must be >= 1 and --warmup >= 0, got {args.steps} and {args.warmup}")
    if args.iteration is not None and args.iteration < 0:
        raise WarpbagsError(f"--iteration must be >= 0, got {args.iteration}")
    context = _warp_cpu_launch()  # a Warp version without it fails before any step
    if not RunFolder(args.run).has_checkpoint():
        raise WarpbagsError(f"{args.run}: no checkpoint to time steps from")
    with tempfile.TemporaryDirectory(prefix="run-steps-") as scratch:
        copy = Path(scratch) / "run"
        shutil.copytree(args.run, copy, ignore=shutil.ignore_patterns("eval", "*.png", "*.mp4"))
        folder = RunFolder(copy)
        info = folder.read_info()
        config = folder.saved_config(info)
        # The scene as the run loaded it (its image level and name), then its training views.
        scene = load_scene(info["scene_root"], resolution=info["resolution"], name=info["scene"])
        trainer = start_or_resume(training_scene(scene, config), config, copy, resume=True, log=lambda message: None)
        if args.iteration is not None:
            trainer.iteration = args.iteration
        if trainer.iteration + args.warmup + args.steps > config.total_iters:
            raise WarpbagsError(f"{args.run}: the run has {config.total_iters - trainer.iteration} iterations left "
                                f"after {trainer.iteration}; pass --iteration N with N + warmup + steps <= "
                                f"{config.total_iters}")
        torch.set_num_threads(1)  # as the trainer: Warp runs its own host threads
        for _ in range(args.warmup):
            trainer.train_step()
        totals, counts = _serial_launch_timer(context)
        wall, cpu = [], []
        for _ in range(args.steps):
            started, started_cpu = time.perf_counter(), time.process_time()
            trainer.train_step()
            wall.append(1e3 * (time.perf_counter() - started))
            cpu.append(1e3 * (time.process_time() - started_cpu))
        step_ms, step_cpu_ms = statistics.median(wall), statistics.median(cpu)
        print(f"{args.run}: iterations {trainer.iteration - args.steps}-{trainer.iteration}, "
              f"{trainer.model.num_gaussians} Gaussians, SH degree {trainer.schedule.sh_degree(trainer.iteration)}, "
              f"{trainer.scene.width}x{trainer.scene.height}, {config.views_per_step or config.views} view(s) per step")
        print(f"step: {step_ms:.0f} ms wall, {step_cpu_ms:.0f} CPU ms ({step_cpu_ms / step_ms:.2f} cores), "
              f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")
        print("Warp launches on the calling thread (serial), ms per step:")
        for (kernel, adjoint), seconds in sorted(totals.items(), key=lambda item: -item[1])[:10]:
            print(f"  {kernel + (' (adjoint)' if adjoint else ''):<56} {1e3 * seconds / args.steps:7.1f}"
                  f"  ({counts[(kernel, adjoint)] / args.steps:.0f} per step)")


if __name__ == "__main__":
    clean_errors(main)()
