"""Rasterization speed: warpbags (Warp kernels) next to the dense torch reference, measured in one run.

    python bench/rasterize.py            # full grid (a few minutes on 2 cores)
    python bench/rasterize.py --quick    # 128^2 only
    python bench/rasterize.py --quick --blocks 1x1,default   # CPU pixel blocks side by side, ratios to the first
    python bench/rasterize.py --device cuda                  # the same grid on a GPU (no dense reference there)

Scene: N Gaussians in a ball of radius 1 seen from C cameras at distance 3.5 (the ball fills about 60% of the
image width), scales shrinking with N^(-1/3). Measured depth complexity (Gaussians within 3 sigma of a covered
pixel): 35 at 128^2 / 10k, 23 at 256^2 / 10k, 54 at 256^2 / 50k, denser than the ~14 of
../shared/NOTES-cpu-rasterizer.md. Each row prints the mean number of Gaussians a pixel visits in its tile's list
(the work the rasterizer actually does). Forward, backward and forward+
backward are medians over repeats (forward+backward: of each repeat's sum); the dense reference (every pixel
against every Gaussian, pixel-chunked, in tests/reference.py, torch on one thread as the whole process is) runs only
where it fits in time, and the last column is its time over ours.

Targets (2-core CPU): 4 cameras, 128^2, 10k Gaussians, forward+backward <= 40 ms (issue 12; 60 ms in the first
round); >= 100x the dense reference at 256^2 / 10k. With --blocks, 1x1 is one pixel per thread (the CUDA layout and
the CPU kernel before pixel blocks); the default CPU block is warpbags.wrapper.DEFAULT_PIXEL_BLOCK.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from conftest import look_at  # noqa: E402
from reference import composite_reference, pixel_centers, project_reference  # noqa: E402
from visits import visits_per_pixel  # noqa: E402

from warpbags.devices import init_warp_quietly  # noqa: E402

init_warp_quietly()  # the table, not Warp's banner and module loads, as the CLI

import warpbags  # noqa: E402
from warpbags.cli.common import clean_errors  # noqa: E402
from warpbags.devices import torch_device  # noqa: E402
from warpbags.errors import WarpbagsError  # noqa: E402
from warpbags.rendering import DEFAULT_TILE_SIZE  # noqa: E402
from warpbags.wrapper import pixel_block_for  # noqa: E402


def bench_scene(n: int, cams: int, size: int, seed: int = 0, device: torch.device = torch.device("cpu")) -> dict:
    """The scene, drawn on the CPU (the same numbers on every device), then moved to `device`."""
    g = torch.Generator().manual_seed(seed)
    direction = torch.randn(n, 3, generator=g)
    radius = torch.rand(n, 1, generator=g) ** (1 / 3)
    means = direction / direction.norm(dim=1, keepdim=True) * radius
    scales = 0.3 * n ** (-1 / 3) * torch.exp(0.3 * torch.randn(n, 3, generator=g))
    viewmats, Ks = [], []
    for c in range(cams):
        angle = 2 * math.pi * c / cams
        eye = torch.tensor([3.5 * math.cos(angle), 3.5 * math.sin(angle), 1.0])
        viewmats.append(look_at(eye, torch.zeros(3)))
        focal = 1.05 * size
        Ks.append(torch.tensor([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1]]))
    scene = dict(
        means=means, quats=torch.randn(n, 4, generator=g), scales=scales,
        opacities=0.1 + 0.8 * torch.rand(n, generator=g), colors=torch.rand(n, 3, generator=g),
        viewmats=torch.stack(viewmats), Ks=torch.stack(Ks), width=size, height=size,
    )
    return {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in scene.items()}


def _synchronize(device: torch.device) -> None:
    """Wait for the device's queued work, so that a clock read after it times the work (CUDA launches return at
    once)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _leaves(scene: dict) -> dict:
    return {k: (v.detach().clone().requires_grad_(k in ("means", "quats", "scales", "opacities", "colors"))
                if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}


def time_warpbags(scene: dict, repeats: int, tile_size: int | None,
                  blocks: list[tuple[int, int] | None] = (None,)) -> dict:
    """Median forward, backward and forward + backward ms (the median of each repeat's sum) and visits per pixel,
    for each CPU pixel block; the blocks take turns within every repeat, so a machine shared with other work slows
    them alike."""
    from warpbags.wrapper import DEFAULT_PIXEL_BLOCK

    default = DEFAULT_PIXEL_BLOCK["cpu"]
    device = scene["means"].device
    times = {block: ([], [], []) for block in blocks}
    try:
        for i in range(repeats + 1):  # the first run compiles / warms caches
            for block in blocks:
                DEFAULT_PIXEL_BLOCK["cpu"] = block if block is not None else default
                leaves = _leaves(scene)
                _synchronize(device)
                t0 = time.perf_counter()
                out, alpha, meta = warpbags.rasterization(**leaves, tile_size=tile_size)
                _synchronize(device)
                t1 = time.perf_counter()
                (out.sum() + alpha.sum()).backward()
                _synchronize(device)
                t2 = time.perf_counter()
                if i:
                    times[block][0].append(t1 - t0)
                    times[block][1].append(t2 - t1)
                    times[block][2].append(t2 - t0)
    finally:
        DEFAULT_PIXEL_BLOCK["cpu"] = default
    visits = visits_per_pixel(meta["bins"], scene["width"], scene["height"])
    return {block: (1e3 * statistics.median(f), 1e3 * statistics.median(b), 1e3 * statistics.median(fb), visits)
            for block, (f, b, fb) in times.items()}


def time_dense(scene: dict, chunk_elements: int = 2**25) -> float:
    """Forward + backward of the dense reference, chunked over pixels to bound memory."""
    leaves = _leaves(scene)
    size, n = scene["width"], scene["means"].shape[0]
    pixels = pixel_centers(size, size, torch.float32)
    chunk = max(1, chunk_elements // n)
    t0 = time.perf_counter()
    for cam in range(scene["viewmats"].shape[0]):
        projected = project_reference(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
                                      leaves["colors"], scene["viewmats"][cam], scene["Ks"][cam], size, size)
        for start in range(0, pixels.shape[0], chunk):
            rgb, _, alpha = composite_reference(projected, pixels[start:start + chunk])
            (rgb.sum() + alpha.sum()).backward(retain_graph=True)
    return 1e3 * (time.perf_counter() - t0)


def _block(text: str) -> tuple[int, int] | None:
    """'WxH', or 'default' for warpbags' CPU default (a block per tile size, see warpbags.wrapper)."""
    if text == "default":
        return None
    width, height = text.lower().split("x")
    return int(width), int(height)


def _counts(text: str) -> list[int]:
    """Comma-separated positive integers (argparse turns the ValueError into a usage error before any timing; this
    bench does not import bench/common.py, which loads OpenCV into the timed process)."""
    counts = [int(item) for item in text.split(",") if item.strip()]
    if not counts or min(counts) < 1:
        raise ValueError(text)
    return counts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="only 128x128")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (after one untimed)")
    parser.add_argument("--tile-size", type=int, default=None, help="default: warpbags' CPU/CUDA default")
    parser.add_argument("--dense-budget-s", type=float, default=210.0, help="skip dense runs expected to exceed this")
    parser.add_argument("--blocks", type=lambda text: [_block(b) for b in text.split(",")], default=None,
                        help="compare CPU pixel blocks (pixels per rasterizer thread), e.g. 1x1,default,2x2: each row "
                             "times every block in turn and prints the first block's f+b time over each other's")
    parser.add_argument("--sizes", type=_counts, default=None, help="comma-separated image sizes (default 128,256,432)")
    parser.add_argument("--gaussians", type=_counts, default="1000,10000,50000", help="comma-separated N")
    parser.add_argument("--cameras", type=_counts, default="1,4", help="comma-separated C")
    parser.add_argument("--device", default="cpu", help="cpu or cuda (the dense reference runs on the CPU only)")
    args = parser.parse_args()
    if args.repeats < 1:
        raise WarpbagsError(f"--repeats must be >= 1, got {args.repeats}")
    if args.tile_size is not None and args.tile_size < 1:
        raise WarpbagsError(f"--tile-size must be >= 1 (pixels), got {args.tile_size}")
    device = torch_device(args.device)
    if args.blocks and device.type != "cpu":
        raise WarpbagsError("--blocks compares CPU pixel blocks: it needs --device cpu")
    tile_size = args.tile_size or DEFAULT_TILE_SIZE[device.type]
    for block in args.blocks or []:
        if block is None:  # "default": whatever the rasterizer makes of its default block, as its label says
            continue
        # the rasterizer shrinks each side to a power of two dividing the tile: the column would name a block that
        # did not run
        try:
            ran = pixel_block_for(device, tile_size, block)
        except ValueError as error:  # more pixels per thread than it has kernels for
            raise WarpbagsError(f"--blocks {block[0]}x{block[1]}: {error}") from None
        if ran != block:
            raise WarpbagsError(f"--blocks {block[0]}x{block[1]}: the rasterizer would run it as {ran[0]}x{ran[1]} "
                                f"on {tile_size} px tiles (each side a power of two dividing the tile)")
    torch.set_num_threads(1)  # Warp uses its own host threads; idle torch OpenMP workers would spin against them

    sizes = args.sizes if args.sizes else [128] if args.quick else [128, 256, 432]
    blocks = args.blocks or [None]
    print(f"warpbags {warpbags.__version__}, torch {torch.__version__}, device {device}, threads "
          f"{torch.get_num_threads()} (torch) / default (Warp), tile size {args.tile_size or 'default'}")
    if args.blocks:
        names = [f"{b[0]}x{b[1]}" if b else "default" for b in blocks]
        header = (f"{'image':>7} {'N':>6} {'C':>2} {'visits/px':>9} "
                  + " ".join(f"{name + ' fwd':>10} {name + ' bwd':>10} {name + ' f+b':>10}" for name in names)
                  + "".join(f" {names[0] + '/' + name:>10}" for name in names[1:]))
    else:
        header = f"{'image':>7} {'N':>6} {'C':>2} {'visits/px':>9} {'fwd ms':>8} {'bwd ms':>8} {'f+b ms':>8} {'dense f+b ms':>13} {'ratio':>7}"
    print(header)
    print("-" * len(header))
    for size in sizes:
        for n in args.gaussians:
            for cams in args.cameras:
                scene = bench_scene(n, cams, size, device=device)
                results = time_warpbags(scene, args.repeats, args.tile_size, blocks)
                visits = results[blocks[0]][3]
                if args.blocks:
                    totals = [results[b][2] for b in blocks]
                    print(f"{size:>4}^2 {n:>6} {cams:>2} {visits:>9.1f} "
                          + " ".join(f"{results[b][0]:>10.1f} {results[b][1]:>10.1f} {t:>10.1f}" for b, t in zip(blocks, totals))
                          + "".join(f" {totals[0] / t:>9.2f}x" for t in totals[1:]), flush=True)
                    continue
                fwd, bwd, total, _ = results[blocks[0]]
                # dense cost ~ pixels x Gaussians x cameras: ~300 ns per pixel-Gaussian pair for fwd+bwd here
                dense_estimate_s = 300e-9 * size * size * n * cams
                dense = (time_dense(scene) if device.type == "cpu" and cams == 1
                         and dense_estimate_s < args.dense_budget_s else None)
                dense_text = f"{dense:13.0f} {dense / total:6.0f}x" if dense else f"{'-':>13} {'-':>7}"
                print(f"{size:>4}^2 {n:>6} {cams:>2} {visits:>9.1f} {fwd:>8.1f} {bwd:>8.1f} {total:>8.1f} {dense_text}",
                      flush=True)


if __name__ == "__main__":
    clean_errors(main)()
