"""A copy of a scene with depth maps of the visual hull of all its views, carved at its reference poses.

    python bench/hull_depths.py SCENE OUT [--resolution 160] [--carve-split 4]
    python bench/pose_recovery.py OUT --seeds 0,1,2 --no-true-pose [--depth monocular]

SCENE: as bench/pose_recovery.py (a preset or a scene folder). OUT: a new folder, a copy of the scene's files with
`depths/<image stem>.npy` added (depth along the optical axis, in the scene folder's own units; 0 where a mask pixel's
ray misses the hull).

What it is for: the synthetic scenes come with exact depth maps and a real capture with none, so whether a real
capture's cameras fail for want of geometry can be measured by giving it geometry. The hull of every view at the
reference poses (maryrose: 69 masks) is close to the object's shape wherever the object is convex, far closer than
any hull of the 4-9 training views; its depth maps stand in for a depth prior much better than a monocular
network's, so a result with them bounds what such a prior could buy. It uses the reference poses and every view:
a measurement, not a method. `--carve-split N` carves with the N training views of the scene's split alone (still
at the reference poses, which the hull then carries into every depth map). The carve keeps a voxel only where every
mask holds it (no missed view), so thin parts that a mask misses are lost and those pixels get no depth.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import check_options, open_bench_scene, resolution_check  # noqa: E402
from warpbags.cameras import camera_centers, pixel_directions, project_points  # noqa: E402
from warpbags.cli.common import clean_errors  # noqa: E402
from warpbags.errors import WarpbagsError  # noqa: E402
from warpbags.init import visual_hull  # noqa: E402

RAYS_PER_CHUNK = 20_000


def occupancy_grid(points: torch.Tensor, voxel: float) -> tuple[torch.Tensor, torch.Tensor]:
    """A boolean grid [X,Y,Z] holding the voxel centres `points` [V,3] of edge `voxel`, and its lower corner [3]
    (half a voxel below the lowest centre: each centre falls in the middle of its cell, not on a rounding edge)."""
    lower = points.min(0).values - 0.5 * voxel
    dims = ((points.max(0).values - lower) / voxel).round().long() + 1
    grid = torch.zeros(*dims.tolist(), dtype=torch.bool)
    index = ((points - lower) / voxel).floor().long()
    grid[index[:, 0], index[:, 1], index[:, 2]] = True
    return grid, lower


def first_hit_depths(grid: torch.Tensor, lower: torch.Tensor, voxel: float, viewmat: torch.Tensor, K: torch.Tensor,
                     pixels: torch.Tensor, near: float, far: float) -> torch.Tensor:
    """[P] depth along the optical axis of the first occupied voxel on each pixel's ray (0 where none), marching in
    half-voxel steps between depths `near` and `far`."""
    dims = torch.tensor(grid.shape)
    origin = camera_centers(viewmat[None])[0]
    directions = pixel_directions(pixels, K) @ viewmat[:3, :3]  # world directions at unit depth
    steps = torch.arange(max(near, 1e-3), far, 0.5 * voxel, dtype=torch.float64)
    depths = torch.zeros(len(pixels), dtype=torch.float64)
    for start in range(0, len(pixels), RAYS_PER_CHUNK):
        chunk = slice(start, start + RAYS_PER_CHUNK)
        samples = origin + directions[chunk, None, :] * steps[None, :, None]  # [R, S, 3]
        cells = ((samples - lower) / voxel).floor().long()
        inside = ((cells >= 0) & (cells < dims)).all(-1)
        cells = torch.minimum(cells.clamp(min=0), dims - 1)
        occupied = grid[cells[..., 0], cells[..., 1], cells[..., 2]] & inside
        first = occupied.int().argmax(1)
        depths[chunk] = torch.where(occupied.any(1), steps[first], torch.zeros(()))
    return depths


def hull_depth_maps(points: torch.Tensor, voxel: float, masks: torch.Tensor, viewmats: torch.Tensor,
                    Ks: torch.Tensor) -> torch.Tensor:
    """[C,H,W] float32 depth maps of a carved hull (`visual_hull`'s voxel centres `points` [V,3] of edge `voxel`)
    seen by cameras [C,4,4] `viewmats`, [C,3,3] `Ks`: along each pixel's ray inside [C,H,W] `masks`, the depth
    (along the optical axis) of the first kept voxel; 0 off the masks and where the ray misses the hull: close to
    the object wherever it is convex."""
    masks = masks.detach().float().cpu()
    viewmats, Ks = viewmats.detach().double().cpu(), Ks.detach().double().cpu()
    depths = torch.zeros(masks.shape, dtype=torch.float32)
    if len(points) == 0:
        return depths
    points = points.detach().double().cpu()
    grid, lower = occupancy_grid(points, voxel)
    center = points.mean(0)
    radius = float((points - center).norm(dim=1).max()) + voxel
    _, distances = project_points(viewmats, Ks, center[None])  # [C, 1]: the centre's depth in each camera
    for view in range(len(masks)):
        rows, cols = torch.nonzero(masks[view] > 0.5, as_tuple=True)
        pixels = torch.stack([cols.double() + 0.5, rows.double() + 0.5], -1)
        distance = float(distances[view, 0])
        view_depths = first_hit_depths(grid, lower, voxel, viewmats[view], Ks[view], pixels, distance - radius,
                                       distance + radius)
        depths[view, rows, cols] = view_depths.float()
    return depths


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene")
    parser.add_argument("out", type=Path)
    parser.add_argument("--resolution", type=int, default=160, help="voxels per axis of the hull's fine pass")
    parser.add_argument("--carve-split", default=None, help="carve with this training split's views only (4, 6, 9)")
    args = parser.parse_args()
    check_options([resolution_check(args.resolution)])
    if args.out.exists():
        raise WarpbagsError(f"{args.out} exists; choose a new folder")
    scene = open_bench_scene(args.scene)
    if scene.masks is None:
        raise WarpbagsError(f"scene {args.scene} has no masks to carve a hull from")
    carved = torch.arange(scene.num_views)
    if args.carve_split is not None:
        if args.carve_split not in scene.splits:
            raise WarpbagsError(f"scene {args.scene} has no split {args.carve_split!r} (it has: "
                                f"{', '.join(sorted(scene.splits))})")
        carved = torch.as_tensor(scene.splits[args.carve_split])
    started = time.perf_counter()
    points, voxel = visual_hull(scene.masks[carved], scene.viewmats[carved], scene.Ks[carved],
                                resolution=args.resolution, missed_views=0)
    if len(points) == 0:
        raise WarpbagsError(f"the masks of {args.scene} leave no voxel at their reference poses")
    depths = hull_depth_maps(points, voxel, scene.masks, scene.viewmats, scene.Ks)
    hit = [float((view_depths[mask > 0.5] > 0).double().mean()) for view_depths, mask in zip(depths, scene.masks)]
    # back to the scene folder's units: a normalized scene's lengths are the source's times its scale
    depths = (depths / scene.normalization.scale).numpy()
    shutil.copytree(scene.root, args.out, symlinks=False)
    (args.out / "depths").mkdir(exist_ok=True)
    for view, name in enumerate(scene.image_names):
        np.save(args.out / "depths" / f"{Path(name).stem}.npy", depths[view])
    print(f"{args.scene}: hull of {len(carved)} views, {len(points)} voxels of {voxel:.4f}; mask pixels with a "
          f"depth: mean {100 * np.mean(hit):.1f}% (min {100 * min(hit):.1f}%); {time.perf_counter() - started:.0f} s "
          f"-> {args.out}")


if __name__ == "__main__":
    clean_errors(main)()
