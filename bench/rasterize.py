"""Rasterization speed: warpbags (Warp kernels) next to the dense torch reference, measured in one run.

    python bench/rasterize.py            # full grid (a few minutes on 2 cores)
    python bench/rasterize.py --quick    # 128^2 only

Scene: N Gaussians in a ball of radius 1 seen from C cameras at distance 3.5 (the ball fills about 60% of the
image width), scales shrinking with N^(-1/3). Measured depth complexity (Gaussians within 3 sigma of a covered
pixel): 35 at 128^2 / 10k, 23 at 256^2 / 10k, 54 at 256^2 / 50k, denser than the ~14 of
../shared/NOTES-cpu-rasterizer.md. Each row prints the mean number of Gaussians a pixel visits in its tile's list
(the work the rasterizer actually does). Forward, backward and forward+
backward are medians over repeats; the dense reference (every pixel against every Gaussian, pixel-chunked, in
tests/reference.py) runs only where it fits in time, and the last column is its time over ours.

Targets (2-core CPU): 4 cameras, 128^2, 10k Gaussians, forward+backward <= 60 ms; >= 100x the dense reference at
256^2 / 10k.
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

import warpbags  # noqa: E402


def bench_scene(n: int, cams: int, size: int, seed: int = 0) -> dict:
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
    return dict(
        means=means, quats=torch.randn(n, 4, generator=g), scales=scales,
        opacities=0.1 + 0.8 * torch.rand(n, generator=g), colors=torch.rand(n, 3, generator=g),
        viewmats=torch.stack(viewmats), Ks=torch.stack(Ks), width=size, height=size,
    )


def _leaves(scene: dict) -> dict:
    return {k: (v.detach().clone().requires_grad_(k in ("means", "quats", "scales", "opacities", "colors"))
                if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}


def time_warpbags(scene: dict, repeats: int, tile_size: int | None) -> tuple[float, float, float]:
    fwd, bwd = [], []
    for i in range(repeats + 1):  # the first run compiles / warms caches
        leaves = _leaves(scene)
        t0 = time.perf_counter()
        out, alpha, meta = warpbags.rasterization(**leaves, tile_size=tile_size)
        t1 = time.perf_counter()
        (out.sum() + alpha.sum()).backward()
        t2 = time.perf_counter()
        if i:
            fwd.append(t1 - t0)
            bwd.append(t2 - t1)
    visits = meta["bins"].isect_ids.numel() * meta["tile_size"] ** 2 / (out.shape[0] * out.shape[1] * out.shape[2])
    f, b = statistics.median(fwd), statistics.median(bwd)
    return 1e3 * f, 1e3 * b, visits


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="only 128x128")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--tile-size", type=int, default=None, help="default: warpbags' CPU/CUDA default")
    parser.add_argument("--dense-budget-s", type=float, default=210.0, help="skip dense runs expected to exceed this")
    args = parser.parse_args()
    torch.set_num_threads(1)  # Warp uses its own host threads; idle torch OpenMP workers would spin against them

    sizes = [128] if args.quick else [128, 256, 432]
    print(f"warpbags {warpbags.__version__}, torch {torch.__version__}, threads {torch.get_num_threads()} (torch) / "
          f"default (Warp), tile size {args.tile_size or 'default'}")
    header = f"{'image':>7} {'N':>6} {'C':>2} {'visits/px':>9} {'fwd ms':>8} {'bwd ms':>8} {'f+b ms':>8} {'dense f+b ms':>13} {'ratio':>7}"
    print(header)
    print("-" * len(header))
    for size in sizes:
        for n in (1_000, 10_000, 50_000):
            for cams in (1, 4):
                scene = bench_scene(n, cams, size)
                fwd, bwd, visits = time_warpbags(scene, args.repeats, args.tile_size)
                # dense cost ~ pixels x Gaussians x cameras: ~300 ns per pixel-Gaussian pair for fwd+bwd here
                dense_estimate_s = 300e-9 * size * size * n * cams
                dense = time_dense(scene) if cams == 1 and dense_estimate_s < args.dense_budget_s else None
                dense_text = f"{dense:13.0f} {dense / (fwd + bwd):6.0f}x" if dense else f"{'-':>13} {'-':>7}"
                print(f"{size:>4}^2 {n:>6} {cams:>2} {visits:>9.1f} {fwd:>8.1f} {bwd:>8.1f} {fwd + bwd:>8.1f} {dense_text}",
                      flush=True)


if __name__ == "__main__":
    main()
