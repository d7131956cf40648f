"""One training step, broken down by phase: maryrose at full resolution (432 x 432), 4 training views.

    python bench/train_step.py                       # random and hull init, 1 and 4 views per step
    python bench/train_step.py --inits random --views 1 --steps 20
    python bench/train_step.py --opensplat PATH      # adds OpenSplat's CPU trainer on the same views and points
    python bench/train_step.py --inits random --views 1 --pixel-blocks 1x1,2x2   # rasterizer pixel blocks compared
    python bench/train_step.py --inits random --views 1 --points 100000 --sh-degree 2   # the paper preset's size
    python bench/train_step.py --device cuda         # the same steps on a GPU

The step is assembled here from pieces `warpbags.trainer.Trainer` uses, not run through `Trainer.train_step`
(configured as the speed comparison with OpenSplat: SH degree 0 unless --sh-degree, no densification, the object on
a white background): `warpbags.init` points and `initial_gaussians`, `warpbags.gaussians.render_gaussians`,
`warpbags.losses`, the Gaussians' Adam groups (`warpbags.model.gaussian_optimizer`), `DensifyStrategy.accumulate`.
The loss is (1-0.2) L1 + 0.2 (1-SSIM) + 0.01 mask BCE on the rendered alpha: no depth term (render mode RGB, as the
trainer renders once the depth term is off) and no silhouette chamfer (the quick preset's `lambda_chamfer` 1). The
poses move by per-camera se(3) deltas (a rotation about the camera centre and a translation) passed straight to
`render_gaussians(pose_deltas=...)` and stepped every iteration by a plain Adam (rotation at the quick preset's
lr.pose, translation at lr.pose x lr.pose_translation_scale), not by the trainer's `CameraOptimizer` (no object-
centric parameterization, preconditioner, pose window or pose lr schedule). Every configuration runs in its own
process, so each peak RSS is its own.

Phases. The rendering stages are timed by wrapping the functions `warpbags.rendering.rasterization` calls
(forward: wall time of each call; backward: identity markers on each stage's inputs and outputs stamp the time
the gradient passes them, and each interval between stamps goes to the stage it ends in). What no stage claims
(activations, compositing the background, autograd bookkeeping, Python) is "other". Warp CPU launches run
serially in the calling thread; warpbags' rasterizer runs host threads over tiles (warpbags/wrapper.py).

Printed per configuration: mean Gaussians per pixel in the tile lists the rasterizer walks, wall ms and CPU ms
(all threads of the process) per phase (medians over the timed steps), the whole step (median of un-instrumented
steps), Warp launches per step and the peak RSS. torch runs with 1 thread, as the trainer sets it. With
`--device cuda` every phase boundary and backward stamp waits for the GPU first (so a phase's wall time is its
kernels' time; its CPU time is then mostly waiting) and the peak of torch's CUDA memory is printed as well; the
pixel blocks and OpenSplat's CPU trainer are CPU comparisons, not offered there. The default
50 warm-up steps match the OpenSplat comparison (/work/shared/tools/opensplat, median after step 50): a random
init's large, overlapping Gaussians shrink and fade over the first steps, so early steps cost more.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import torch

from visits import visits_per_pixel

PHASES = (
    "pose deltas", "projection", "SH", "binning + sort", "raster forward", "loss forward",
    "loss backward", "raster backward", "SH backward", "projection backward", "pose backward",
    "densify stats", "optimizer", "other",
)
# The stages `warpbags.rendering` imports from `warpbags.wrapper`, keyed by its name for them.
STAGES = {
    "apply_pose_deltas": ("pose deltas", "pose backward"),
    "project_gaussians": ("projection", "projection backward"),
    "spherical_harmonics": ("SH", "SH backward"),
    "bin_gaussians": ("binning + sort", None),
    "rasterize_to_pixels": ("raster forward", "raster backward"),
}
OPENSPLAT_BACKGROUND = (0.6130, 0.0101, 0.3984)  # OpenSplat's fixed training background (model.hpp)


def _no_wait() -> None:
    pass


# What a clock reading waits for first: the GPU's queued work with --device cuda (`run_configuration` sets it).
_wait_for_device = _no_wait


class _Stamp(torch.autograd.Function):
    """Identity whose backward records (time, label): where the backward pass is at that moment."""

    @staticmethod
    def forward(ctx, tensor, events, label):
        ctx.events, ctx.label = events, label
        return tensor.view_as(tensor)

    @staticmethod
    def backward(ctx, grad):
        _wait_for_device()
        ctx.events.append((time.perf_counter(), time.process_time(), ctx.label))
        return grad, None, None


class PhaseClock:
    """Accumulates the wall ms and the CPU ms (all threads of the process) of each phase within one step."""

    def __init__(self):
        self.ms = dict.fromkeys(PHASES, 0.0)
        self.cpu_ms = dict.fromkeys(PHASES, 0.0)
        self.events: list[tuple[float, float, str]] = []  # backward stamps (wall, CPU, label) of the current step

    @staticmethod
    def now() -> tuple[float, float]:
        _wait_for_device()
        return time.perf_counter(), time.process_time()

    def add(self, name: str, start: tuple[float, float], end: tuple[float, float]) -> None:
        self.ms[name] += 1e3 * (end[0] - start[0])
        self.cpu_ms[name] += 1e3 * (end[1] - start[1])

    @contextmanager
    def phase(self, name: str):
        start = self.now()
        yield
        self.add(name, start, self.now())

    def attribute_backward(self, start: tuple[float, float], end: tuple[float, float]) -> None:
        """Split [start, end] of loss.backward() among the stages by the stamps seen in it.

        An interval ending at a stage's input stamp was that stage's backward; one ending at the rasterizer's
        output stamps was the loss (and compositing) backward; the rest is glue ("other").
        """
        last = start
        for wall, cpu, label in sorted(self.events):
            stage, side = label.rsplit(":", 1)
            if side == "in":
                phase = STAGES[stage][1]
            elif stage == "rasterize_to_pixels":
                phase = "loss backward"
            else:
                phase = "other"
            self.add(phase, last, (wall, cpu))
            last = (wall, cpu)
        self.add("other", last, end)
        self.events.clear()


def _stamped(tensor, clock: PhaseClock, label: str):
    if isinstance(tensor, torch.Tensor) and tensor.is_floating_point() and tensor.requires_grad:
        return _Stamp.apply(tensor, clock.events, label)
    return tensor


@contextmanager
def instrumented(clock: PhaseClock):
    """Wrap the stages `warpbags.rendering` calls with forward timers and backward stamps; count Warp launches."""
    import warp as wp

    import warpbags.rendering as rendering

    originals = {name: getattr(rendering, name) for name in STAGES}
    launches = [0]
    launch = wp.launch

    def counted_launch(*args, **kwargs):
        launches[0] += 1
        return launch(*args, **kwargs)

    def wrap(name, function):
        forward_phase = STAGES[name][0]

        def stage(*args, **kwargs):
            args = [_stamped(a, clock, f"{name}:in") for a in args]
            with clock.phase(forward_phase):
                outputs = function(*args, **kwargs)
            if isinstance(outputs, tuple) and not hasattr(outputs, "_fields"):
                return tuple(_stamped(o, clock, f"{name}:out") for o in outputs)
            return _stamped(outputs, clock, f"{name}:out")

        return stage

    for name, function in originals.items():
        setattr(rendering, name, wrap(name, function))
    wp.launch = counted_launch
    try:
        yield launches
    finally:
        for name, function in originals.items():
            setattr(rendering, name, function)
        wp.launch = launch


def build_problem(init: str, points: int, seed: int = 0, sh_degree: int = 0,
                  device: torch.device = torch.device("cpu")) -> dict:
    """The 4 training views of maryrose at full resolution, initial Gaussians and optimizers (as the trainer), the
    points drawn on the CPU (the same on every device) and everything the steps touch on `device`."""
    from warpbags.configs.train import DensifyConfig, load_preset
    from warpbags.init import hull_or_random_points, initial_gaussians
    from warpbags.model import gaussian_optimizer, scene_extent
    from warpbags.strategy import DensifyStrategy
    from warpbags.trainer import training_scene

    config = load_preset("quick", max_image_size=0, init=init, init_points=points, sh_degree=sh_degree, views_per_step=1,
                         seed=seed)
    scene = training_scene("maryrose", config)
    generator = torch.Generator().manual_seed(seed)
    xyz, colors, note = hull_or_random_points(
        scene.images, scene.masks, scene.viewmats, scene.Ks, method=init, count=points,
        resolution=config.hull_resolution, dilation_px=config.hull_dilation_px,
        missed_views=config.hull_missed_views, generator=generator,
    )
    params = {name: torch.nn.Parameter(value.to(device))
              for name, value in initial_gaussians(xyz, colors, sh_degree).items()}
    extent = scene_extent(scene.viewmats)
    optimizer = gaussian_optimizer(params, config, extent)
    lr = config.lr
    cams = scene.num_views
    pose_rotations = torch.nn.Parameter(torch.zeros(cams, 3, device=device))
    pose_translations = torch.nn.Parameter(torch.zeros(cams, 3, device=device))
    pose_optimizer = torch.optim.Adam([{"params": [pose_rotations], "lr": lr.pose},
                                       {"params": [pose_translations], "lr": lr.pose * lr.pose_translation_scale}])
    # Statistics accumulate every step; no clone/split/prune ever runs (fixed Gaussian count, as OpenSplat's run).
    strategy = DensifyStrategy(DensifyConfig(start=10**9, stop=10**9 + 1, opacity_reset_every=0, floater_every=0),
                               extent)
    masks = scene.masks.to(device)
    targets = scene.on_background(1.0).to(device)  # the object on the white background
    return dict(scene=scene, viewmats=scene.viewmats.to(device), Ks=scene.Ks.to(device), config=config,
                params=params, optimizer=optimizer, pose_rotations=pose_rotations,
                pose_translations=pose_translations, pose_optimizer=pose_optimizer, strategy=strategy,
                targets=targets, masks=masks, backgrounds=torch.ones(cams, 3, device=device), init_note=note,
                points=xyz, point_colors=colors, generator=torch.Generator().manual_seed(seed))


def training_step(problem: dict, views_per_step: int, clock: PhaseClock | None = None) -> dict:
    """One step of the problem (the module docstring: not `Trainer.train_step`, whose poses move through its
    `CameraOptimizer` and whose loss has the chamfer term); returns the render's meta."""
    from warpbags.gaussians import render_gaussians
    from warpbags.losses import mask_loss, photometric_loss

    clock = clock or PhaseClock()
    scene, config = problem["scene"], problem["config"]
    views = torch.randperm(scene.num_views, generator=problem["generator"])[:views_per_step]
    with clock.phase("other"):
        deltas = torch.cat([problem["pose_rotations"], problem["pose_translations"]], dim=1)[views]
    renders, alphas, meta = render_gaussians(
        problem["params"], problem["viewmats"][views], problem["Ks"][views], scene.width, scene.height,
        sh_degree=config.sh_degree,
        backgrounds=problem["backgrounds"][views], pose_deltas=deltas, render_mode="RGB",
    )
    meta["means2d"].retain_grad()
    with clock.phase("loss forward"):
        loss, _ = photometric_loss(renders[..., :3], problem["targets"][views], config.lambda_dssim)
        loss = loss + config.lambda_mask * mask_loss(alphas[..., 0], problem["masks"][views])
    start = clock.now()
    loss.backward()
    clock.attribute_backward(start, clock.now())
    with clock.phase("densify stats"):
        problem["strategy"].accumulate(0, meta)
    with clock.phase("optimizer"):
        problem["optimizer"].step()
        problem["optimizer"].zero_grad(set_to_none=True)
        problem["pose_optimizer"].step()
        problem["pose_optimizer"].zero_grad(set_to_none=True)
    return meta


def run_configuration(init: str, views_per_step: int, points: int, steps: int, warmup: int,
                      pixel_block: tuple[int, int] | None = None, sh_degree: int = 0, device: str = "cpu") -> dict:
    """Median ms per phase over `steps` instrumented steps, then the median of `steps` plain steps; `pixel_block`
    replaces the rasterizer's default CPU block (warpbags.wrapper.DEFAULT_PIXEL_BLOCK) for the whole run."""
    global _wait_for_device
    from warpbags.devices import torch_device
    from warpbags.wrapper import DEFAULT_PIXEL_BLOCK

    target = torch_device(device)
    if target.type == "cuda":
        _wait_for_device = functools.partial(torch.cuda.synchronize, target)
    else:
        torch.set_num_threads(1)  # as the trainer: Warp runs its own host threads
    if pixel_block is not None:
        DEFAULT_PIXEL_BLOCK["cpu"] = pixel_block
    problem = build_problem(init, points, sh_degree=sh_degree, device=target)
    for _ in range(warmup):
        training_step(problem, views_per_step)
    # the plain steps first, right after the warm-up: the window OpenSplat's steps are timed in (early steps cost
    # more, the random init's Gaussians shrinking and fading); the instrumented steps after them
    plain, plain_cpu = [], []
    for _ in range(steps):
        start, start_cpu = PhaseClock.now()
        training_step(problem, views_per_step)
        end, end_cpu = PhaseClock.now()
        plain.append(1e3 * (end - start))
        plain_cpu.append(1e3 * (end_cpu - start_cpu))
    per_phase: dict[str, list[float]] = {name: [] for name in PHASES}
    per_phase_cpu: dict[str, list[float]] = {name: [] for name in PHASES}
    launch_counts = []
    visits = []
    for _ in range(steps):
        clock = PhaseClock()
        with instrumented(clock) as launches:
            start = clock.now()
            meta = training_step(problem, views_per_step, clock)
            end = clock.now()
        clock.ms["other"] += 1e3 * (end[0] - start[0]) - sum(clock.ms.values())
        clock.cpu_ms["other"] += 1e3 * (end[1] - start[1]) - sum(clock.cpu_ms.values())
        for name in PHASES:
            per_phase[name].append(clock.ms[name])
            per_phase_cpu[name].append(clock.cpu_ms[name])
        launch_counts.append(launches[0])
        visits.append(visits_per_pixel(meta["bins"], meta["width"], meta["height"]))
    scene = problem["scene"]
    return {
        "init": init, "views_per_step": views_per_step, "gaussians": len(problem["params"]["means"]),
        "pixel_block": "x".join(map(str, DEFAULT_PIXEL_BLOCK["cpu"])),
        "init_note": problem["init_note"], "width": scene.width, "height": scene.height,
        "phases_ms": {name: statistics.median(values) for name, values in per_phase.items()},
        "phases_cpu_ms": {name: statistics.median(values) for name, values in per_phase_cpu.items()},
        "step_ms": statistics.median(plain), "step_cpu_ms": statistics.median(plain_cpu), "step_ms_instrumented": statistics.median(
            [sum(values[i] for values in per_phase.values()) for i in range(steps)]),
        "launches": statistics.median(launch_counts), "visits_per_pixel": statistics.fmean(visits),
        "peak_rss_mib": _high_water_kib(os.getpid()) / 1024, "device": str(target),
        "peak_cuda_mib": torch.cuda.max_memory_allocated(target) / 2**20 if target.type == "cuda" else None,
    }


def write_opensplat_project(folder: Path, points: int) -> dict:
    """The random-init problem as an OpenSplat (nerfstudio) project: the same 4 views, intrinsics and 10k points.

    As /work/shared/tools/opensplat/perf_vs_opensplat_prep.py: transforms.json with OpenGL camera axes, the object
    composited onto OpenSplat's fixed background (the analogue of warpbags' white one), points.ply with uchar
    colours. Cameras and points stay in warpbags' normalized world (OpenSplat re-centres and scales both alike).
    """
    import cv2
    import numpy as np

    problem = build_problem("random", points)
    scene = problem["scene"]
    (folder / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    opengl_axes = np.diag([1.0, -1.0, -1.0, 1.0])
    composites = scene.on_background(OPENSPLAT_BACKGROUND)
    for index in range(scene.num_views):
        rgb = (composites[index].clamp(0, 1) * 255).round().to(torch.uint8).numpy()
        name = f"images/view_{index}.png"
        cv2.imwrite(str(folder / name), rgb[..., ::-1])
        K = scene.Ks[index].double()
        camera_to_world = np.linalg.inv(scene.viewmats[index].double().numpy()) @ opengl_axes
        frames.append({"file_path": name, "w": scene.width, "h": scene.height, "fl_x": float(K[0, 0]),
                       "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
                       "transform_matrix": camera_to_world.tolist()})
    xyz = problem["points"].numpy().astype("<f4")
    colors = (problem["point_colors"].clamp(0, 1) * 255).round().to(torch.uint8).numpy()
    rows = np.empty(len(xyz), dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    rows["xyz"], rows["rgb"] = xyz, colors
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\nproperty float x\nproperty float y\n"
              "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    with open(folder / "points.ply", "wb") as handle:
        handle.write(header.encode("ascii"))
        handle.write(rows.tobytes())
    transforms = {"camera_model": "OPENCV", "ply_file_path": "points.ply", "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(transforms, indent=2))
    return {"width": scene.width, "height": scene.height, "points": len(xyz)}


def run_opensplat(binary: Path, points: int, steps: int, warmup: int) -> dict:
    """OpenSplat's CPU trainer on the same problem (SH 0, no densification, 0.2 DSSIM, full resolution, one view
    per step): median interval between its "Step N" lines after `warmup`, and its own peak RSS."""
    with tempfile.TemporaryDirectory(prefix="opensplat-") as work:
        folder = Path(work)
        write_opensplat_project(folder, points)
        command = [str(binary), str(folder), "-o", str(folder / "splat.ply"), "-n", str(warmup + steps + 1), "--cpu",
                   "-d", "1", "--num-downscales", "0", "--sh-degree", "0", "--ssim-weight", "0.2",
                   "--warmup-length", "1000000", "--refine-every", "1000000", "--densify-grad-thresh", "1e9",
                   "--save-every", "-1"]
        process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
        step_line = re.compile(r"^Step ([0-9]+):")
        stamps = {}
        peak_kib = 0
        last = ""  # its last line of output, said if it fails
        for line in process.stdout:
            last = line.strip() or last
            match = step_line.match(line)
            if match:
                stamps[int(match.group(1))] = time.perf_counter()
                peak_kib = max(peak_kib, _high_water_kib(process.pid))
        process.wait()
    if process.returncode != 0 or len(stamps) < warmup + 2:
        from warpbags.errors import WarpbagsError  # noqa: PLC0415 - the parent alone imports it, as in main

        raise WarpbagsError(f"--opensplat {binary}: exited with code {process.returncode} after {len(stamps)} "
                            f"\"Step N:\" lines, needed {warmup + 2} or more; its last line: {last or '(none)'}")
    intervals = [stamps[s] - stamps[s - 1] for s in sorted(stamps) if s > warmup and s - 1 in stamps]
    return {"step_ms": 1e3 * statistics.median(intervals), "peak_rss_mib": peak_kib / 1024}


def _high_water_kib(pid: int) -> int:
    """VmHWM of a running process: its peak RSS since exec (a child's ru_maxrss would include the forked copy
    of this Python process)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except OSError:  # it has just exited
        pass
    return 0


def _child(arguments: list[str]) -> dict:
    """Run this script for one configuration in a fresh process (its own peak RSS) and read its JSON line."""
    result = subprocess.run([sys.executable, __file__, *arguments], capture_output=True, text=True, check=False)
    if result.returncode != 0:
        from warpbags.errors import WarpbagsError  # noqa: PLC0415 - the parent alone imports it, as in main

        # the child's traceback ends with its exception: one line to print, not the traceback
        lines = result.stderr.strip().splitlines() or [f"exit code {result.returncode}"]
        raise WarpbagsError(f"the configuration {' '.join(arguments)} failed: {lines[-1]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def print_table(rows: list[dict], opensplat: dict | None) -> None:
    blocks = {r["pixel_block"] for r in rows}
    names = [f"{r['init']} {r['views_per_step']}v" + (f" {r['pixel_block']}" if len(blocks) > 1 else "") for r in rows]
    width = max(len(n) for n in PHASES + ("step (plain)",)) + 1
    print(f"{'':<{width}}" + "".join(f"{n:>17}" for n in names))
    for key, label, fmt in (("gaussians", "Gaussians", "{:17d}"), ("visits_per_pixel", "visits / pixel", "{:17.1f}"),
                            ("launches", "Warp launches", "{:17.0f}")):
        print(f"{label:<{width}}" + "".join(fmt.format(r[key]) for r in rows))
    print("wall ms per phase (median over steps) | CPU ms, all threads:")
    for phase in PHASES:
        print(f"  {phase:<{width - 2}}" + "".join(f"{r['phases_ms'][phase]:8.1f} |{r['phases_cpu_ms'][phase]:7.1f}"
                                                    for r in rows))
    print(f"{'sum of phases':<{width}}" + "".join(f"{r['step_ms_instrumented']:8.1f} |{'':7}" for r in rows))
    print(f"{'step (plain)':<{width}}" + "".join(f"{r['step_ms']:8.1f} |{r['step_cpu_ms']:7.1f}" for r in rows))
    print(f"{'peak RSS MiB':<{width}}" + "".join(f"{r['peak_rss_mib']:17.0f}" for r in rows))
    if rows[0]["peak_cuda_mib"] is not None:
        print(f"{'peak CUDA MiB':<{width}}" + "".join(f"{r['peak_cuda_mib']:17.0f}" for r in rows))
    if len(blocks) > 1:  # the first block's step time over each other block's, same init and views
        first = {}
        for r, name in zip(rows, names):
            key = (r["init"], r["views_per_step"])
            if key not in first:
                first[key] = r
            else:
                base = first[key]
                print(f"  {name}: step {base['step_ms'] / r['step_ms']:.2f}x, raster forward "
                      f"{base['phases_ms']['raster forward'] / r['phases_ms']['raster forward']:.2f}x, raster backward "
                      f"{base['phases_ms']['raster backward'] / r['phases_ms']['raster backward']:.2f}x faster than "
                      f"pixel block {base['pixel_block']}")
    if opensplat is not None:
        print(f"OpenSplat (CPU), one view per step: {opensplat['step_ms']:.0f} ms/step, {opensplat['peak_rss_mib']:.0f} MiB")
        for r, name in zip(rows, names):
            if r["views_per_step"] == 1 and r["init"] == "random":  # OpenSplat's problem: random init, SH 0
                print(f"  warpbags {name} per step: {opensplat['step_ms'] / r['step_ms']:.1f}x faster than OpenSplat, "
                      f"peak RSS {r['peak_rss_mib']:.0f} vs {opensplat['peak_rss_mib']:.0f} MiB")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--inits", default="random,hull", help="comma-separated: random, hull")
    parser.add_argument("--views", default="1,4", help="comma-separated views per step")
    parser.add_argument("--points", type=int, default=10_000, help="initial Gaussians")
    parser.add_argument("--steps", type=int, default=20, help="timed steps per configuration")
    parser.add_argument("--sh-degree", type=int, default=0,
                        help="SH degree of the Gaussians' colours (the paper preset ends at 2; OpenSplat runs at 0)")
    parser.add_argument("--warmup", type=int, default=50, help="untimed steps first (compilation, the early steps)")
    parser.add_argument("--opensplat", type=Path, help="an OpenSplat binary built with its CPU backend")
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--pixel-blocks", default=None,
                        help="comma-separated CPU pixel blocks to compare (e.g. 1x1,2x2; 1x1 is one pixel per "
                             "rasterizer thread, the layout before blocks); default: the rasterizer's default block")
    parser.add_argument("--one", nargs=2, metavar=("INIT", "VIEWS"), help=argparse.SUPPRESS)  # a child process
    parser.add_argument("--block", default=None, help=argparse.SUPPRESS)  # the child's pixel block
    args = parser.parse_args()
    if args.one:
        block = tuple(int(v) for v in args.block.split("x")) if args.block else None
        print(json.dumps(run_configuration(args.one[0], int(args.one[1]), args.points, args.steps, args.warmup,
                                           block, args.sh_degree, args.device)))
        return
    from common import check_json, write_json  # noqa: PLC0415 - not in the children: their peak RSS is measured
    from warpbags.cli.common import parse_numbers  # noqa: PLC0415
    from warpbags.configs.train import load_preset  # noqa: PLC0415
    from warpbags.devices import torch_device  # noqa: PLC0415
    from warpbags.errors import WarpbagsError  # noqa: PLC0415
    from warpbags.rendering import DEFAULT_TILE_SIZE  # noqa: PLC0415
    from warpbags.wrapper import pixel_block_for  # noqa: PLC0415

    device = torch_device(args.device)
    if device.type == "cuda" and (args.pixel_blocks or args.opensplat):
        raise WarpbagsError("--pixel-blocks and --opensplat compare CPU rasterizers and trainers: "
                            "not with --device cuda")
    if args.opensplat and args.sh_degree != 0:
        raise WarpbagsError(f"--opensplat runs OpenSplat at SH degree 0: compare with --sh-degree 0, not "
                            f"{args.sh_degree}")
    if not 0 <= args.sh_degree <= 3:
        raise WarpbagsError(f"--sh-degree must be 0-3, got {args.sh_degree}")
    # checked here, not found missing after every configuration has been timed
    if args.opensplat and not (args.opensplat.is_file() and os.access(args.opensplat, os.X_OK)):
        raise WarpbagsError(f"--opensplat {args.opensplat}: not an executable file")
    inits = [init for init in args.inits.split(",") if init]
    if not inits or any(init not in ("random", "hull") for init in inits):
        raise WarpbagsError(f"--inits {args.inits!r}: expected comma-separated random, hull")
    views_per_step = parse_numbers(args.views, "--views", int, minimum=1)
    # a step draws its views from the training views (build_problem's scene: the quick preset's view count), so a
    # larger count would render them all and be labelled as more
    training_views = load_preset("quick").views
    if max(views_per_step) > training_views:
        raise WarpbagsError(f"--views {args.views!r}: a step renders at most maryrose's {training_views} training "
                            f"views, not {max(views_per_step)}")
    blocks = [block for block in args.pixel_blocks.split(",") if block] if args.pixel_blocks else [None]
    tile_size = DEFAULT_TILE_SIZE[device.type]
    for block in blocks:
        if block is None:
            continue
        if not re.fullmatch(r"[1-9][0-9]*x[1-9][0-9]*", block):
            raise WarpbagsError(f"--pixel-blocks {args.pixel_blocks!r}: {block!r} is not WIDTHxHEIGHT (e.g. 2x2)")
        # the rasterizer shrinks each side to a power of two dividing the tile: the column would name a block
        # that did not run
        width, height = pixel_block_for(device, tile_size, tuple(int(side) for side in block.split("x")))
        if block != f"{width}x{height}":
            raise WarpbagsError(f"--pixel-blocks {args.pixel_blocks!r}: the rasterizer would run {block} as "
                                f"{width}x{height} on its {tile_size} px tiles (each side a power of two dividing "
                                "the tile)")
    if args.steps < 1 or args.warmup < 0 or args.points < 1:
        raise WarpbagsError(f"--steps and --points must be >= 1 and --warmup >= 0, got {args.steps}, {args.points} "
                            f"and {args.warmup}")
    check_json(args.json)  # written after every configuration has run
    rows = []
    for init in inits:
        for views in views_per_step:
            for block in blocks:
                rows.append(_child(["--one", init, str(views), "--points", str(args.points), "--steps", str(args.steps),
                                    "--warmup", str(args.warmup), "--sh-degree", str(args.sh_degree),
                                    "--device", args.device,
                                    *(["--block", block] if block else [])]))
    opensplat = None
    if args.opensplat is not None:
        opensplat = run_opensplat(args.opensplat, args.points, args.steps, args.warmup)
    first = rows[0]
    where = (f"{torch.cuda.get_device_name(device)}" if device.type == "cuda"
             else f"torch {torch.__version__} (1 thread), {len(os.sched_getaffinity(0))} cores")
    print(f"maryrose {first['width']}x{first['height']}, 4 training views, {where}; init: "
          + "; ".join(f"{r['init']}: {r['init_note']}" for r in rows[::len(views_per_step) * len(blocks)]))
    print_table(rows, opensplat)
    if args.json is not None:
        write_json(args.json, {"rows": rows, "opensplat": opensplat}, indent=2)


if __name__ == "__main__":
    if "--one" in sys.argv[1:]:  # a child (see _child): nothing more imported, its peak RSS is the configuration's
        main()
    else:
        from warpbags.cli.common import clean_errors  # bad input: one line and exit code 2, as the CLI

        clean_errors(main)()
