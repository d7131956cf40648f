"""The work the rasterizer does per pixel, printed by the speed benchmarks (bench/rasterize.py, bench/train_step.py).
Not in bench/common.py: that loads OpenCV and the data code, which those scripts keep out of the processes they time
and whose peak RSS they measure; this imports torch alone."""

from __future__ import annotations

import torch


def visits_per_pixel(bins, width: int, height: int) -> float:
    """The mean over the image's pixels (all cameras') of the Gaussians in the list of the tile each pixel is in.

    Args:
        bins: the `warpbags.wrapper.TileBins` of a render of `width` x `height` images (its meta's "bins").

    A tile on the right or bottom edge counts only its pixels inside the image: where the tile size does not divide
    the image, whole tiles cover more pixels than the image has, and counting them over-counts the visits (a 64 px
    tile over an 8 px image, 64 times).
    """
    size = bins.tile_size
    counts = bins.tile_offsets.diff().reshape(-1, bins.tiles_y, bins.tiles_x).cpu().double()
    columns = (width - size * torch.arange(bins.tiles_x, dtype=torch.float64)).clamp(max=size)
    rows = (height - size * torch.arange(bins.tiles_y, dtype=torch.float64)).clamp(max=size)
    return float((counts * rows[:, None] * columns).sum()) / (counts.shape[0] * width * height)
