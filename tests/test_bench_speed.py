"""The speed benchmarks (bench/rasterize.py, bench/train_step.py): which runs and steps their clocks time, and the
visits per pixel they print. The rasterizer and the training step are stubbed by ones that advance a fake clock by
a known time per call, so that each median names the calls it was taken over."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import rasterize  # noqa: E402
import train_step  # noqa: E402
from visits import visits_per_pixel  # noqa: E402


def _bins(tile_size: int, tiles_x: int, tiles_y: int, counts: list[int]) -> SimpleNamespace:
    """A `warpbags.wrapper.TileBins` with `counts` Gaussians in the lists of the tiles (cameras, rows, columns)."""
    offsets = torch.cumsum(torch.tensor([0, *counts], dtype=torch.int32), 0, dtype=torch.int32)
    return SimpleNamespace(tile_size=tile_size, tiles_x=tiles_x, tiles_y=tiles_y, tile_offsets=offsets,
                           isect_ids=torch.zeros(sum(counts), dtype=torch.int32))


# a 10 x 6 image in 4 px tiles: 3 x 2 tiles of 16, 16, 8 / 8, 8, 4 pixels in the image, holding 1-6 Gaussians
EDGE_BINS = _bins(4, 3, 2, [1, 2, 3, 4, 5, 6])
EDGE_VISITS = (1 * 16 + 2 * 16 + 3 * 8 + 4 * 8 + 5 * 8 + 6 * 4) / 60  # 2.8; whole tiles would count 21 * 16 / 60


def test_visits_per_pixel_counts_the_pixels_of_edge_tiles_inside_the_image():
    assert visits_per_pixel(EDGE_BINS, 10, 6) == pytest.approx(EDGE_VISITS)
    # tiles that divide the image (the README's 128, 256 and 432 px at 4 or 16 px tiles): every tile's pixels count,
    # as they did before, over all cameras
    counts = [3, 0, 7, 1, 2, 2, 5, 4]  # 2 cameras of 2 x 2 tiles
    assert visits_per_pixel(_bins(4, 2, 2, counts), 8, 8) == sum(counts) * 16 / (2 * 8 * 8)


def test_rasterize_visits_of_a_tile_larger_than_the_image_are_at_most_the_gaussians():
    """100 Gaussians over an 8 px image in one 64 px tile: each pixel visits at most all 100 (was: 6400, the tile's
    4096 pixels counted over the image's 64)."""
    scene = rasterize.bench_scene(100, 1, 8)
    [(_, _, _, visits)] = rasterize.time_warpbags(scene, repeats=1, tile_size=64).values()
    assert 0 < visits <= 100


def test_rasterize_times_every_repeat_but_the_first(monkeypatch):
    """The first run of each block compiles the kernels and warms the caches: of repeats + 1 runs, the medians are
    over the last `repeats`. Run k (from 0) takes k + 1 s forward and 10 (k + 1) s backward."""
    clock = [0.0]
    calls = []

    def rasterization(means, tile_size, **_):
        calls.append(tile_size)
        clock[0] += len(calls)
        backward_seconds = 10.0 * len(calls)
        out = means.sum() * torch.ones(1, 8, 8, 3)

        def backward(grad):
            clock[0] += backward_seconds
            return grad

        out.register_hook(backward)
        return out, torch.zeros(1, 8, 8, 1), {"bins": _bins(8, 1, 1, [5]), "tile_size": 8}

    monkeypatch.setattr(rasterize, "warpbags", SimpleNamespace(rasterization=rasterization))
    monkeypatch.setattr(rasterize, "time", SimpleNamespace(perf_counter=lambda: clock[0]))
    scene = {"means": torch.zeros(3, 3), "width": 8, "height": 8}
    [(forward, backward, total, visits)] = rasterize.time_warpbags(scene, repeats=2, tile_size=8).values()
    assert calls == [8, 8, 8]
    # runs 1 and 2 (2 and 3 s forward, 20 and 30 s backward); with run 0 timed too the medians would be 2, 20, 22 s
    assert (forward, backward, total) == pytest.approx((2500.0, 25000.0, 27500.0))
    assert visits == 5.0


def test_train_step_times_the_steps_right_after_the_warmup(monkeypatch):
    """`warmup` untimed steps, then `steps` plain steps timed (the window OpenSplat's steps are timed in), then
    `steps` instrumented ones. Step k (from 0) takes k + 1 ms of wall and of CPU time."""
    clock = [0.0]
    steps_run = []

    def training_step(problem, views_per_step, clock_=None):
        steps_run.append(views_per_step)
        clock[0] += 1e-3 * len(steps_run)
        return {"bins": EDGE_BINS, "width": 10, "height": 6, "n_cameras": 1}

    monkeypatch.setattr(train_step, "build_problem", lambda init, points, sh_degree, device: {
        "params": {"means": torch.zeros(7, 3)}, "init_note": "stub", "scene": SimpleNamespace(width=10, height=6)})
    monkeypatch.setattr(train_step, "training_step", training_step)
    monkeypatch.setattr(train_step, "time", SimpleNamespace(perf_counter=lambda: clock[0],
                                                            process_time=lambda: clock[0]))
    row = train_step.run_configuration("random", 1, points=7, steps=3, warmup=2)
    assert len(steps_run) == 2 + 3 + 3
    # steps 2-4 plain (3, 4, 5 ms), steps 5-7 instrumented (6, 7, 8 ms, all "other" here: no stage ran)
    assert row["step_ms"] == pytest.approx(4.0) and row["step_cpu_ms"] == pytest.approx(4.0)
    assert row["step_ms_instrumented"] == pytest.approx(7.0) and row["phases_ms"]["other"] == pytest.approx(7.0)
    assert row["visits_per_pixel"] == pytest.approx(EDGE_VISITS)
