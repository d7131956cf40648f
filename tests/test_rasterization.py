"""warpbags.rasterization against the dense torch reference (tests/reference.py) and finite differences."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch
from conftest import DEVICES, random_scene
from reference import render_reference

import warpbags

DIFFERENTIABLE = ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks", "backgrounds", "pose_deltas")


def assert_gradients_close(ours_in, ref_in):
    """Float64 gradients agree to 1e-8 of each input's largest gradient (T is recovered by division backward)."""
    for name in DIFFERENTIABLE:
        expected = ref_in[name].grad
        torch.testing.assert_close(ours_in[name].grad, expected, rtol=1e-7, atol=1e-8 * expected.abs().max().item(),
                                   msg=lambda m: f"{name}: {m}")


def _inputs(scene, cams, seed=1):
    g = torch.Generator().manual_seed(seed)
    dtype = scene["means"].dtype
    extra = dict(
        backgrounds=torch.rand(cams, 3, generator=g, dtype=dtype),
        pose_deltas=0.02 * torch.randn(cams, 6, generator=g, dtype=dtype),
    )
    return {k: v for k, v in {**scene, **extra}.items()}


def _split(inputs):
    tensors = {k: v.detach().clone().requires_grad_(True) for k, v in inputs.items() if k in DIFFERENTIABLE}
    return tensors, inputs["width"], inputs["height"]


def _render_both(inputs, sh_degree=None, tile_size=4, **planes_and_eps2d):
    tensors, w, h = _split(inputs)
    ours, alpha, _ = warpbags.rasterization(**tensors, width=w, height=h, sh_degree=sh_degree, render_mode="RGB+D",
                                            tile_size=tile_size, **planes_and_eps2d)
    ref_tensors, _, _ = _split(inputs)
    ref_rgb, ref_depth, ref_alpha = render_reference(**ref_tensors, width=w, height=h, sh_degree=sh_degree,
                                                     **planes_and_eps2d)
    return (tensors, torch.cat([ours, alpha], -1)), (ref_tensors, torch.cat([ref_rgb, ref_depth, ref_alpha], -1))


def _assert_matches_reference(inputs, sh_degree=None, tile_size=4, **planes_and_eps2d):
    """Our float64 image, depth and alpha equal the dense reference's, and so do the gradients of every input under
    one random cotangent."""
    (ours_in, ours), (ref_in, ref) = _render_both(inputs, sh_degree, tile_size, **planes_and_eps2d)
    assert ref[..., 4].max() > 0.5, "the scene should cover part of the image"
    torch.testing.assert_close(ours, ref, rtol=1e-9, atol=1e-9)
    cotangent = torch.randn(ours.shape, generator=torch.Generator().manual_seed(7), dtype=ours.dtype)
    (ours * cotangent).sum().backward()
    (ref * cotangent).sum().backward()
    assert_gradients_close(ours_in, ref_in)


@pytest.mark.parametrize("cams,sh_degree,tile_size", [(1, None, 4), (3, None, 8), (2, 3, 16), (3, 1, 4)])
def test_matches_dense_reference_forward_and_backward_float64(cams, sh_degree, tile_size):
    inputs = _inputs(random_scene(n=40, cams=cams, width=26, height=19, sh_degree=sh_degree, seed=cams), cams)
    _assert_matches_reference(inputs, sh_degree, tile_size)


def test_matches_dense_reference_float32():
    inputs = _inputs(random_scene(n=60, cams=2, width=32, height=32, dtype=torch.float32, seed=5), 2)
    (_, ours), _ = _render_both(inputs)
    inputs64 = {k: (v.double() if isinstance(v, torch.Tensor) else v) for k, v in inputs.items()}
    _, (_, ref) = _render_both(inputs64)
    torch.testing.assert_close(ours.double(), ref, rtol=1e-4, atol=2e-4)


def test_near_plane_and_eps2d_match_dense_reference():
    """No other test sets either (a `rasterization` that ignored them passed): a near plane through the ball culls
    its nearer Gaussians, a smaller low-pass sharpens every splat."""
    near_plane, eps2d = 3.0, 0.1
    inputs = _inputs(random_scene(n=40, cams=2, width=26, height=19, seed=6), 2)
    _, _, meta = warpbags.rasterization(**{k: v for k, v in inputs.items() if k != "pose_deltas"})
    depths = meta["depths"][meta["radii"] > 0]
    assert (depths < near_plane - 0.1).sum() > 10 and (depths > near_plane + 0.1).sum() > 10  # it cuts the ball
    _assert_matches_reference(inputs, near_plane=near_plane, eps2d=eps2d)


def test_early_termination_matches_reference_and_gradients():
    """Opaque Gaussians stacked along the view ray: T falls below 1e-4 and compositing stops early."""
    scene = random_scene(n=12, cams=1, width=12, height=12, seed=3, spread=0.05, scale_range=(0.3, 0.4))
    scene["opacities"] = torch.full_like(scene["opacities"], 0.95)
    inputs = _inputs(scene, 1)
    (ours_in, ours), (ref_in, ref) = _render_both(inputs)
    assert (1 - ref[..., 4]).min() < 1e-3  # transmittance near the 1e-4 floor somewhere
    torch.testing.assert_close(ours, ref, rtol=1e-9, atol=1e-9)
    # Termination skipped contributions: compositing every Gaussian gives a visibly different image.
    reference_inputs, width, height = _split(inputs)
    every = torch.cat(render_reference(**reference_inputs, width=width, height=height, early_termination=False), -1)
    assert (every.detach() - ref.detach()).abs().max() > 1e-4
    ours.sum().backward()
    ref.sum().backward()
    assert_gradients_close(ours_in, ref_in)


def test_the_alpha_clamp_matches_reference_and_gradients():
    """Gaussians of opacity up to 1 whose centres cover pixels: alpha is clamped at 0.99 there (3DGS), and the
    clamp's zero gradient is what the reference's min() gives."""
    scene = random_scene(n=10, cams=1, width=12, height=12, seed=4, spread=0.3, scale_range=(1.5, 2.0))
    scene["opacities"] = torch.linspace(0.99, 1.0, 10, dtype=torch.float64)
    _, _, meta = warpbags.rasterization(**scene)
    ys, xs = torch.meshgrid(torch.arange(12.0, dtype=torch.float64) + 0.5, torch.arange(12.0, dtype=torch.float64) + 0.5,
                            indexing="ij")
    dx, dy = xs[..., None] - meta["means2d"][0, :, 0], ys[..., None] - meta["means2d"][0, :, 1]
    a, b, c = meta["conics"][0].unbind(-1)
    raw = scene["opacities"] * torch.exp(-(0.5 * (a * dx ** 2 + c * dy ** 2) + b * dx * dy))
    assert (raw > 0.99).sum() >= 3  # pixels where the clamp applies
    inputs = _inputs(scene, 1)
    (ours_in, ours), (ref_in, ref) = _render_both(inputs)
    torch.testing.assert_close(ours, ref, rtol=1e-9, atol=1e-9)
    ours.sum().backward()
    ref.sum().backward()
    assert_gradients_close(ours_in, ref_in)


@pytest.mark.parametrize("sh_degree", [None, 2])
def test_gradcheck_float64_every_input(sh_degree):
    """Finite differences (float64) against the analytic gradient of every differentiable input."""
    inputs = _inputs(random_scene(n=8, cams=2, width=10, height=9, seed=11, sh_degree=sh_degree), 2)
    tensors, w, h = _split(inputs)
    names = list(tensors)

    def render(*args):
        rgbd, alpha, _ = warpbags.rasterization(**dict(zip(names, args)), width=w, height=h, sh_degree=sh_degree,
                                                render_mode="RGB+ED")
        return torch.cat([rgbd, alpha], -1)

    assert torch.autograd.gradcheck(render, tuple(tensors.values()), eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)


def test_pose_delta_gradient_matches_finite_differences_at_zero():
    """Every camera starts at delta = 0, where the exp map switches to its series branch."""
    inputs = _inputs(random_scene(n=15, cams=2, width=14, height=12, seed=4), 2)
    tensors, w, h = _split(inputs)
    deltas = torch.zeros(2, 6, dtype=torch.float64, requires_grad=True)
    fixed = {k: v.detach() for k, v in tensors.items() if k != "pose_deltas"}

    def render(d):
        return warpbags.rasterization(**fixed, pose_deltas=d, width=w, height=h)[0]

    assert torch.autograd.gradcheck(render, (deltas,), eps=1e-7, atol=1e-6, rtol=1e-5)


def test_cpu_threads_give_identical_results():
    inputs = _inputs(random_scene(n=80, cams=2, width=40, height=30, seed=9), 2)
    results = []
    for threads in (1, 2, 3, 0):  # 0: the default, every usable core
        tensors, w, h = _split(inputs)
        out, _, _ = warpbags.rasterization(**tensors, width=w, height=h, cpu_threads=threads)
        out.square().sum().backward()
        results.append([out] + [tensors[k].grad for k in DIFFERENTIABLE])
    for other in results[1:]:
        for a, b in zip(results[0], other):
            torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("tile_size", [4, 8, 16])
@pytest.mark.parametrize("cams,threads", [(3, 1), (3, 4), (1, 3)])
def test_counting_sort_binning_equals_key_sort(dtype, tile_size, cams, threads):
    """The CPU binning (counting sort of depth-ordered Gaussians, each camera's depth order in chunks on host
    threads) lists exactly what the CUDA path's key sort does."""
    from warpbags.wrapper import _bin_by_sort, _tile_geometry, _to_warp, bin_gaussians, project_gaussians

    n, width, height = 200, 37, 29
    scene = random_scene(n=n, cams=cams, width=width, height=height, dtype=dtype, seed=1)
    means2d, conics, depths, radii = project_gaussians(scene["means"], scene["quats"], scene["scales"],
                                                       scene["opacities"], scene["viewmats"], scene["Ks"], width, height)
    bins = bin_gaussians(means2d, conics, scene["opacities"], radii, depths, width, height, tile_size,
                         cpu_threads=threads)
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    splats = dict(means2d=_to_warp(means2d.reshape(-1, 2).contiguous(), "vec2"),
                  conics=_to_warp(conics.reshape(-1, 3).contiguous(), "vec3"),
                  opacities=_to_warp(scene["opacities"], "scalar"), radii=_to_warp(radii.reshape(-1).contiguous(), "int32"))
    tiles = _tile_geometry(n, width, height, tile_size)
    tile_offsets, isect_ids = _bin_by_sort(splats, tiles, depths, cams * tiles_x * tiles_y)
    assert len(isect_ids) > 4 * cams * tiles_x * tiles_y  # several Gaussians per tile
    assert torch.equal(bins.tile_offsets, tile_offsets) and torch.equal(bins.isect_ids, isect_ids)
    # Gaussians at equal depths are listed in index order by both (a sort that is not stable may swap them), and
    # float64 depths closer than a float32 step in depth order (a key of their float32 bits would tie them)
    for offset in (0.0, -1e-12):
        tied = depths.clone()
        tied[:, 1::2] = tied[:, ::2][:, :n // 2] + offset
        bins = bin_gaussians(means2d, conics, scene["opacities"], radii, tied, width, height, tile_size,
                             cpu_threads=threads)
        tile_offsets, isect_ids = _bin_by_sort(splats, tiles, tied, cams * tiles_x * tiles_y)
        assert torch.equal(bins.tile_offsets, tile_offsets) and torch.equal(bins.isect_ids, isect_ids)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_nan_gaussian_is_culled_and_a_screen_filling_one_kept(dtype):
    """Culling is NaN-safe: a Gaussian with a NaN mean is culled (on the CPU its radius became INT_MIN, which the
    backward pass visited, making every pose gradient of its cameras NaN); a footprint beyond int32 is clamped, not
    wrapped to a negative radius that culled a Gaussian covering the whole image."""
    scene = random_scene(n=20, cams=2, width=16, height=12, seed=2, dtype=dtype)
    scene["means"] = scene["means"].clone()
    scene["means"][0] = math.nan
    deltas = torch.zeros(2, 6, dtype=dtype, requires_grad=True)
    out, _, meta = warpbags.rasterization(**scene, pose_deltas=deltas)
    out.sum().backward()
    assert torch.all(meta["radii"][:, 0] == 0) and torch.isfinite(out).all()
    assert torch.isfinite(deltas.grad).all() and deltas.grad.abs().sum() > 0
    scene = random_scene(n=20, cams=2, width=16, height=12, seed=2, dtype=dtype)
    scene["scales"] = scene["scales"].clone()
    scene["scales"][0] = 1e9
    _, alphas, meta = warpbags.rasterization(**scene)
    assert torch.all(meta["radii"][:, 0] == 2**30)
    assert alphas.min() >= 0.99 * scene["opacities"][0]  # it covers every pixel


def test_binning_refuses_counts_beyond_int32_offsets(monkeypatch):
    """Offsets and indices are int32 in the kernels: past the limit they would wrap (out-of-bounds writes on a GPU,
    where nothing checks); both binning paths say so instead. The limit is lowered to what a small scene reaches."""
    from warpbags import wrapper

    scene = random_scene(n=200, cams=2, width=16, height=12, seed=1)
    means2d, conics, depths, radii = wrapper.project_gaussians(scene["means"], scene["quats"], scene["scales"],
                                                               scene["opacities"], scene["viewmats"], scene["Ks"], 16, 12)
    bins = wrapper.bin_gaussians(means2d, conics, scene["opacities"], radii, depths, 16, 12, 4)
    splats = dict(means2d=wrapper._to_warp(means2d.reshape(-1, 2).contiguous(), "vec2"),
                  conics=wrapper._to_warp(conics.reshape(-1, 3).contiguous(), "vec3"),
                  opacities=wrapper._to_warp(scene["opacities"], "scalar"),
                  radii=wrapper._to_warp(radii.reshape(-1).contiguous(), "int32"))
    assert len(bins.isect_ids) > 2 * max(200, 16 * 12)  # above the other limits
    monkeypatch.setattr(wrapper, "INT32_LIMIT", len(bins.isect_ids))
    with pytest.raises(ValueError, match="Gaussian-tile intersections exceed int32"):
        wrapper.bin_gaussians(means2d, conics, scene["opacities"], radii, depths, 16, 12, 4)
    with pytest.raises(ValueError, match="Gaussian-tile intersections exceed int32"):  # the CUDA path's
        wrapper._bin_by_sort(splats, wrapper._tile_geometry(200, 16, 12, 4), depths, 2 * 4 * 3)
    monkeypatch.setattr(wrapper, "INT32_LIMIT", 2 * 16 * 12)
    with pytest.raises(ValueError, match="2 cameras x 200 Gaussians or x 16x12 pixels exceed int32"):
        wrapper.bin_gaussians(means2d, conics, scene["opacities"], radii, depths, 16, 12, 4)


def test_spherical_harmonics_refuses_fewer_coefficients_than_its_degree_reads():
    """The kernel reads (degree + 1)^2 coefficients per Gaussian: with fewer it read past the tensor (garbage
    colours such as 1e275, no error)."""
    from warpbags.wrapper import spherical_harmonics

    scene = random_scene(n=5, cams=1)
    with pytest.raises(ValueError, match=r"degree 3 \(0-3\) needs coeffs \[N = 5, K >= 16, 3\], got \[5, 1, 3\]"):
        spherical_harmonics(scene["means"], torch.rand(5, 1, 3, dtype=torch.float64), scene["viewmats"], 3)
    with pytest.raises(ValueError, match=r"needs coeffs \[N = 5, K >= 16, 3\], got \[2, 16, 3\]"):  # too few rows
        spherical_harmonics(scene["means"], torch.rand(2, 16, 3, dtype=torch.float64), scene["viewmats"], 3)
    colors = spherical_harmonics(scene["means"], torch.zeros(5, 16, 3, dtype=torch.float64), scene["viewmats"], 3)
    assert torch.equal(colors, torch.full((1, 5, 3), 0.5, dtype=torch.float64))


@pytest.mark.parametrize("render_mode,channels", [("RGB", 3), ("D", 1), ("ED", 1), ("RGB+D", 4), ("RGB+ED", 4)])
def test_render_modes(render_mode, channels):
    """Every mode against the independent dense renderer: colour, accumulated depth (D) and expected depth (ED,
    D / alpha, which the depth loss and the viewer use) wherever the pixel is covered."""
    scene = random_scene(n=20, cams=2, width=16, height=12, seed=2)
    out, alpha, meta = warpbags.rasterization(**scene, render_mode=render_mode)
    assert out.shape == (2, 12, 16, channels)
    assert alpha.shape == (2, 12, 16, 1)
    ref_rgb, ref_depth, ref_alpha = render_reference(**scene)
    torch.testing.assert_close(alpha, ref_alpha)
    covered = ref_alpha[..., 0] > 0.05
    assert covered.float().mean() > 0.2  # the Gaussians cover a good part of each image
    expected = {"RGB": ref_rgb, "D": ref_depth, "ED": ref_depth / ref_alpha.clamp_min(1e-10)}
    for name, channels_out in zip(render_mode.split("+"), torch.split(out, [3 if m == "RGB" else 1
                                                                             for m in render_mode.split("+")], -1)):
        if name == "ED":
            torch.testing.assert_close(channels_out[covered], expected[name][covered])
            assert channels_out[covered].min() > 2.0 and channels_out[covered].max() < 4.0  # cameras ~3 from the ball
        else:
            torch.testing.assert_close(channels_out, expected[name])


@pytest.mark.parametrize("device", DEVICES)
def test_edge_cases(device):
    dtype = torch.float32
    base = random_scene(n=10, cams=2, width=20, height=8, dtype=dtype, device=device)  # non-square

    def render(**overrides):
        scene = {**base, **overrides}
        out, alpha, meta = warpbags.rasterization(**scene)
        assert torch.isfinite(out).all() and torch.isfinite(alpha).all()
        return out, alpha, meta

    # zero Gaussians
    empty = {k: base[k][:0] for k in ("means", "quats", "scales", "opacities", "colors")}
    out, alpha, _ = render(**empty)
    assert out.shape == (2, 8, 20, 3) and alpha.abs().max() == 0

    # all beyond the far plane: the Gaussians sit 2.5-3.9 in front of both cameras (they render); far plane at 1.5
    _, alpha, meta = render()
    assert (meta["radii"] > 0).any() and alpha.max() > 0
    _, alpha, meta = render(far_plane=1.5)
    assert (meta["radii"] == 0).all() and alpha.max() == 0

    viewmats = base["viewmats"].clone()
    viewmats[:, :3, :3] = -viewmats[:, :3, :3]  # cameras turned around: everything is behind them
    viewmats[:, :3, 3] = -viewmats[:, :3, 3]
    _, alpha, meta = render(viewmats=viewmats)
    assert (meta["radii"] == 0).all() and alpha.max() == 0

    # all off-screen: shift the principal point far outside the image
    Ks = base["Ks"].clone()
    Ks[:, 0, 2] += 1000.0
    _, alpha, meta = render(Ks=Ks)
    assert (meta["radii"] == 0).all() and alpha.max() == 0

    # degenerate (zero) scales: the 0.3 px low-pass keeps them finite and visible
    _, alpha, _ = render(scales=torch.zeros_like(base["scales"]))
    assert alpha.max() > 0

    # huge scales: one Gaussian covers the whole image
    _, alpha, _ = render(scales=torch.full_like(base["scales"], 100.0))
    assert alpha.min() > 0.5

    # one camera
    out, _, _ = render(viewmats=base["viewmats"][:1], Ks=base["Ks"][:1])
    assert out.shape == (1, 8, 20, 3)


def test_gradient_reaches_each_camera_only_through_its_pixels():
    scene = random_scene(n=30, cams=3, width=16, height=16, seed=8)
    deltas = torch.zeros(3, 6, dtype=torch.float64, requires_grad=True)
    out, _, _ = warpbags.rasterization(**scene, pose_deltas=deltas)
    out[1].sum().backward()
    assert deltas.grad[1].abs().sum() > 0
    assert deltas.grad[0].abs().sum() == 0 and deltas.grad[2].abs().sum() == 0


@pytest.mark.parametrize(
    "override,message",
    [
        (dict(render_mode="RGBD"), "render_mode"),
        (dict(sh_degree=4), "sh_degree"),
        (dict(backgrounds=torch.zeros(3, 3, dtype=torch.float64)), "backgrounds"),
        (dict(pose_deltas=torch.zeros(2, 3, dtype=torch.float64)), "pose_deltas"),
        # float32 Ks with float64 means reached Warp, whose bad overload failed every later render in the process
        (dict(Ks=torch.eye(3).expand(2, 3, 3)), "Ks is torch.float32 on cpu; expected torch.float64 on cpu"),
        (dict(backgrounds=torch.zeros(2, 3)), "backgrounds is torch.float32 on cpu; expected torch.float64 on cpu"),
        (dict(backgrounds=torch.zeros(2, 3, dtype=torch.float64, device="meta")),
         "backgrounds is torch.float64 on meta; expected torch.float64 on cpu"),
        (dict(colors=torch.zeros(5, 3)), "colors is torch.float32 on cpu; expected torch.float64 on cpu"),
        (dict(colors=torch.zeros(5, 1, dtype=torch.float64)),
         "colors must be [N, 3] or [C, N, 3] RGB (or set sh_degree), got [5, 1]"),
        # a [4, 4] viewmats counted 4 cameras and blamed Ks ("Ks must have shape [4, 3, 3]")
        (dict(viewmats=torch.eye(4, dtype=torch.float64)), "viewmats must have shape [C, 4, 4], got [4, 4]"),
        # scalars reached Warp or torch unchecked: a float or bool was a Warp type error, a negative size a torch
        # error after the projection ran, cpu_threads=-1 a range error; a negative near plane rendered what is
        # behind the camera
        (dict(width=-5), "width must be an int >= 0, got -5"),
        (dict(height=-1), "height must be an int >= 0, got -1"),
        (dict(width=24.0), "width must be an int >= 0, got 24.0"),
        (dict(sh_degree=True, colors=torch.zeros(5, 4, 3, dtype=torch.float64)),
         "sh_degree must be an int from 0 to 3, got True"),
        (dict(sh_degree=-1), "sh_degree must be an int from 0 to 3, got -1"),
        (dict(cpu_threads=-1), "cpu_threads must be an int >= 0, got -1"),
        (dict(cpu_threads=2.5), "cpu_threads must be an int >= 0, got 2.5"),
        (dict(near_plane=-5.0), "the planes must satisfy 0 < near_plane < far_plane, got near_plane=-5.0, "
                                "far_plane=10000000000.0"),
        (dict(near_plane=0.0), "got near_plane=0.0"),
        (dict(near_plane=2.0, far_plane=1.0), "got near_plane=2.0, far_plane=1.0"),
        (dict(near_plane=math.nan), "got near_plane=nan"),
        (dict(eps2d=-0.1), "eps2d must be >= 0 (pixels^2), got -0.1"),
    ],
)
def test_bad_arguments_are_named(override, message):
    """Each refused before any kernel runs, with the argument and its value; the next render is unaffected."""
    scene = random_scene(n=5, cams=2)
    before, _, _ = warpbags.rasterization(**scene)
    with pytest.raises(ValueError, match=re.escape(message)):
        warpbags.rasterization(**{**scene, **override})
    after, _, _ = warpbags.rasterization(**scene)
    assert torch.equal(after, before)


def test_numpy_integers_and_a_zero_size_image_are_accepted():
    """Integers reach Warp as Python ints (a numpy integer was a Warp type error); a zero-size image renders as an
    empty one."""
    scene = random_scene(n=10, cams=2, width=24, height=20, sh_degree=1)
    expected, _, _ = warpbags.rasterization(**scene, sh_degree=1)
    out, _, meta = warpbags.rasterization(**{**scene, "width": np.int64(24), "height": np.int32(20)},
                                          sh_degree=np.int64(1), cpu_threads=np.int64(2))
    assert torch.equal(out, expected) and type(meta["width"]) is int and type(meta["height"]) is int
    means = scene["means"].clone().requires_grad_(True)
    out, alpha, _ = warpbags.rasterization(**{**scene, "means": means, "width": 0}, sh_degree=1)
    assert out.shape == (2, 20, 0, 3) and alpha.shape == (2, 20, 0, 1)
    out.sum().backward()
    assert torch.equal(means.grad, torch.zeros_like(means))


def test_second_derivatives_are_refused_by_name():
    """Every backward writes its gradients with Warp kernels into fresh buffers, constants to torch: under
    create_graph a Hessian-vector product silently lacked the render's term. Each stage refuses; first derivatives
    still work."""
    from warpbags.wrapper import apply_pose_deltas, fused_photometric_loss, project_gaussians, spherical_harmonics

    scene = random_scene(n=10, cams=2, width=12, height=10, sh_degree=1, seed=4)
    means = scene["means"].clone().requires_grad_(True)
    deltas = torch.full((2, 6), 0.01, dtype=torch.float64, requires_grad=True)
    images = torch.rand(2, 10, 12, 3, dtype=torch.float64, requires_grad=True)
    stages = {
        "rasterize_to_pixels": (means, lambda: warpbags.rasterization(**{**scene, "means": means}, sh_degree=1,
                                                                      pose_deltas=deltas)[0]),
        "project_gaussians": (means, lambda: project_gaussians(means, scene["quats"], scene["scales"],
                                                               scene["opacities"], scene["viewmats"], scene["Ks"],
                                                               12, 10)[0]),
        "spherical_harmonics": (means, lambda: spherical_harmonics(means, scene["colors"], scene["viewmats"], 1)),
        "kernel apply_pose_deltas_kernel": (deltas, lambda: apply_pose_deltas(scene["viewmats"], deltas)),
        "fused_photometric_loss": (images, lambda: fused_photometric_loss(images, torch.rand_like(images), 0.2)[0]),
    }
    for name, (leaf, output) in stages.items():
        with pytest.raises(RuntimeError, match=f"^{name}: first derivatives only"):
            torch.autograd.grad(output().square().sum(), leaf, create_graph=True)
        (gradient,) = torch.autograd.grad(output().square().sum(), leaf)
        assert gradient.abs().sum() > 0, name


def test_tile_sizes_cameras_and_dtypes_the_kernels_cannot_take_are_named():
    """A tile of 0 px was a ZeroDivisionError, of -4 a `max()` of nothing; no camera at all was a ZeroDivisionError
    in the binning; int64 means blamed the quaternions ("quats is torch.float64; expected torch.int64")."""
    scene = random_scene(n=5, cams=2)
    for tile_size in (0, -4, 2.5, True):
        with pytest.raises(ValueError, match=f"tile_size must be an int >= 1, got {tile_size!r}"):
            warpbags.rasterization(**scene, tile_size=tile_size)
    colors, _, _ = warpbags.rasterization(**scene, tile_size=np.int64(4))  # numpy integers as the image size's
    torch.testing.assert_close(colors, warpbags.rasterization(**scene, tile_size=4)[0], rtol=0, atol=0)
    with pytest.raises(ValueError, match="viewmats must hold at least one camera"):
        warpbags.rasterization(**{**scene, "viewmats": scene["viewmats"][:0], "Ks": scene["Ks"][:0]})
    with pytest.raises(ValueError, match="^means must be float32 or float64, got torch.int64"):
        warpbags.rasterization(**{**scene, "means": scene["means"].long()})


@pytest.mark.parametrize("tile_size", [3, 6, 18])
def test_tile_sizes_that_are_not_a_power_of_two_match_the_reference(tile_size):
    """Every tile size divisible by 3 and not by 4 was refused on the CPU ("pixel block 3x3")."""
    inputs = _inputs(random_scene(n=30, cams=2, width=23, height=19, seed=4), 2)
    (ours_in, ours), (ref_in, ref) = _render_both(inputs, None, tile_size)
    torch.testing.assert_close(ours, ref, rtol=1e-9, atol=1e-9)
    ours.sum().backward()
    ref.sum().backward()
    assert_gradients_close(ours_in, ref_in)


def test_cpu_threads_hold_every_stage_forward_and_backward(monkeypatch):
    """`cpu_threads` reached the binning and the rasterizer only: the projection and SH stages, forward and
    backward, were cut over every usable core (`render_threads=1` used two cores here)."""
    import threading

    import warpbags.wrapper as wrapper

    monkeypatch.setattr(wrapper, "_default_cpu_threads", lambda: 4)  # as on a 4-core machine
    monkeypatch.setattr(wrapper, "MIN_PAIRS_PER_THREAD", 4)  # a small scene cut as a large one would be
    launched_from: dict[str, set[str]] = {}
    launch = wrapper._Launcher.launch

    def recording_launch(self, kernel, dim, /, **arguments):
        launched_from.setdefault(kernel.key, set()).add(threading.current_thread().name)
        return launch(self, kernel, dim, **arguments)

    monkeypatch.setattr(wrapper._Launcher, "launch", recording_launch)
    inputs = random_scene(n=60, cams=2, width=24, height=20, sh_degree=1, seed=3)
    for threads, expect_pool in ((1, False), (None, True)):
        launched_from.clear()
        tensors, w, h = _split(inputs)
        out, _, _ = warpbags.rasterization(**tensors, width=w, height=h, sh_degree=1, cpu_threads=threads)
        out.sum().backward()
        stages = [key for key in launched_from if key.startswith(("project_gaussians", "sh_to_colors"))]
        assert len(stages) == 4, launched_from  # projection and SH, forward and backward
        assert all((launched_from[key] != {"MainThread"}) is expect_pool for key in stages), launched_from


def test_float32_refuses_more_gaussians_than_it_counts_exactly(monkeypatch):
    """The kernels count a pixel's place in its tile's list in the float type; float32 is exact below 2^24 entries,
    so more Gaussians per camera are refused by name (the limit lowered here to 5 to keep the scene small)."""
    import warpbags.wrapper as wrapper

    monkeypatch.setattr(wrapper, "_FLOAT32_EXACT_COUNT", 5)
    with pytest.raises(ValueError, match="2\\^24 Gaussians per camera, got 5"):
        warpbags.rasterization(**random_scene(n=5, cams=1, dtype=torch.float32))
    warpbags.rasterization(**random_scene(n=5, cams=1))  # float64 counts exactly far beyond


# Pixel blocks: on the CPU one rasterizer thread composites a block of a tile (warpbags.wrapper.DEFAULT_PIXEL_BLOCK);
# one pixel per thread is the CUDA layout. Every block must give the dense reference's image and gradients.
PIXEL_BLOCKS = [(1, 1), (2, 1), (1, 2), (2, 2), (4, 1), (4, 2), (2, 4), (4, 4)]


@pytest.mark.parametrize("block", PIXEL_BLOCKS)
@pytest.mark.parametrize("tile_size", [4, 8])
def test_pixel_blocks_match_dense_reference_float64(block, tile_size, monkeypatch):
    """26 x 19 pixels: neither side divides by the tile or the block, so edge blocks hold pixels outside the image."""
    monkeypatch.setitem(warpbags.wrapper.DEFAULT_PIXEL_BLOCK, "cpu", block)
    inputs = _inputs(random_scene(n=40, cams=2, width=26, height=19, seed=6), 2)
    _assert_matches_reference(inputs, tile_size=tile_size)


@pytest.mark.parametrize("block", [(1, 1), (2, 2), (4, 2)])
def test_pixel_blocks_early_termination(block, monkeypatch):
    """Opaque stacked Gaussians: lanes of one block stop compositing at different list entries."""
    monkeypatch.setitem(warpbags.wrapper.DEFAULT_PIXEL_BLOCK, "cpu", block)
    scene = random_scene(n=12, cams=1, width=13, height=11, seed=3, spread=0.05, scale_range=(0.3, 0.4))
    scene["opacities"] = torch.full_like(scene["opacities"], 0.95)
    inputs = _inputs(scene, 1)
    (ours_in, ours), (ref_in, ref) = _render_both(inputs)
    assert (1 - ref[..., 4]).min() < 1e-3
    torch.testing.assert_close(ours, ref, rtol=1e-9, atol=1e-9)
    ours.sum().backward()
    ref.sum().backward()
    assert_gradients_close(ours_in, ref_in)


def test_pixel_blocks_agree_with_one_pixel_per_thread():
    """The image is bitwise the one-pixel kernel's (same per-pixel arithmetic); gradients differ only by the order
    in which a block's pixels are summed before they reach the buffers."""
    from warpbags.wrapper import bin_gaussians, project_gaussians, rasterize_to_pixels

    scene = random_scene(n=120, cams=2, width=37, height=29, seed=12)
    means2d, conics, depths, radii = project_gaussians(scene["means"], scene["quats"], scene["scales"],
                                                       scene["opacities"], scene["viewmats"], scene["Ks"], 37, 29)
    colors = scene["colors"].expand(2, -1, -1).contiguous()
    bins = bin_gaussians(means2d, conics, scene["opacities"], radii, depths, 37, 29, 4)
    cotangents = [torch.randn(2, 29, 37, *shape, generator=torch.Generator().manual_seed(s), dtype=torch.float64)
                  for s, shape in ((1, (3,)), (2, ()), (3, ()))]
    results = {}
    for block in PIXEL_BLOCKS:
        leaves = [t.detach().clone().requires_grad_() for t in (means2d, conics, colors, scene["opacities"], depths)]
        outputs = rasterize_to_pixels(*leaves, bins, 37, 29, pixel_block=block)
        sum((o * v).sum() for o, v in zip(outputs, cotangents)).backward()
        results[block] = (outputs, [leaf.grad for leaf in leaves])
    (one_out, one_grads) = results[(1, 1)]
    for block, (outputs, grads) in results.items():
        for a, b in zip(outputs, one_out):
            assert torch.equal(a, b), block
        for a, b in zip(grads, one_grads):
            torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12 * b.abs().max().item(), msg=lambda m: f"{block}: {m}")


@pytest.mark.parametrize("block", [(1, 1), (4, 4)])
def test_loss_without_depth_takes_the_backward_without_depth_terms(block, monkeypatch):
    """A loss that does not use the depth map gets the kernel without its terms, with the gradients of the full
    kernel given a zero depth cotangent (the same arithmetic minus exact zeros)."""
    from warpbags.wrapper import bin_gaussians, project_gaussians, rasterize_to_pixels

    used = []

    class Recording(dict):
        def __getitem__(self, key):
            used.append(key)
            return super().__getitem__(key)

    monkeypatch.setattr(warpbags.wrapper, "BACKWARD_KERNELS", Recording(warpbags.wrapper.BACKWARD_KERNELS))
    scene = random_scene(n=120, cams=2, width=37, height=29, seed=13)
    means2d, conics, depths, radii = project_gaussians(scene["means"], scene["quats"], scene["scales"],
                                                       scene["opacities"], scene["viewmats"], scene["Ks"], 37, 29)
    colors = scene["colors"].expand(2, -1, -1).contiguous()
    bins = bin_gaussians(means2d, conics, scene["opacities"], radii, depths, 37, 29, 4)
    v_colors, v_alphas = (torch.randn(2, 29, 37, *shape, generator=torch.Generator().manual_seed(s),
                                      dtype=torch.float64) for s, shape in ((1, (3,)), (3, ())))
    grads = []
    for depth_weight in (None, 0.0):
        leaves = [t.detach().clone().requires_grad_() for t in (means2d, conics, colors, scene["opacities"], depths)]
        out_colors, out_depths, out_alphas = rasterize_to_pixels(*leaves, bins, 37, 29, pixel_block=block)
        loss = (out_colors * v_colors).sum() + (out_alphas * v_alphas).sum()
        if depth_weight is not None:
            loss = loss + depth_weight * out_depths.sum()
        loss.backward()
        grads.append([leaf.grad for leaf in leaves])
    lanes = block[0] * block[1]
    assert used == [(lanes, False), (lanes, True)]
    for without, full in zip(*grads):
        torch.testing.assert_close(without, full, rtol=1e-12, atol=1e-12 * full.abs().max().item())
    assert grads[0][0].abs().max() > 0


@pytest.mark.parametrize("block", [(1, 1), (2, 2), (4, 2)])
def test_float32_backward_matches_float64_reference(block, monkeypatch):
    """float32 image and gradients against the float64 dense reference: within 2e-4 of the image and 2e-3 of each
    input's largest gradient (float32 rounding accumulated over ~60 Gaussians per pixel and the division that
    recovers T backward)."""
    monkeypatch.setitem(warpbags.wrapper.DEFAULT_PIXEL_BLOCK, "cpu", block)
    inputs = _inputs(random_scene(n=60, cams=2, width=30, height=21, dtype=torch.float32, seed=5), 2)
    (ours_in, ours), _ = _render_both(inputs)
    inputs64 = {k: (v.double() if isinstance(v, torch.Tensor) else v) for k, v in inputs.items()}
    _, (ref_in, ref) = _render_both(inputs64)
    torch.testing.assert_close(ours.double(), ref, rtol=1e-4, atol=2e-4)
    cotangent = torch.randn(ours.shape, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    (ours * cotangent.float()).sum().backward()
    (ref * cotangent).sum().backward()
    for name in DIFFERENTIABLE:
        expected = ref_in[name].grad
        torch.testing.assert_close(ours_in[name].grad.double(), expected, rtol=0,
                                   atol=2e-3 * expected.abs().max().item(), msg=lambda m: f"{name}: {m}")


def test_pixel_block_fits_the_tile():
    from warpbags.wrapper import pixel_block_for

    cpu = torch.device("cpu")
    assert pixel_block_for(cpu, 4, (4, 2)) == (4, 2)
    assert pixel_block_for(cpu, 2, (4, 4)) == (2, 2)  # a block never spans two tiles
    assert pixel_block_for(cpu, 4, (3, 1)) == (2, 1)  # each side the largest power of two dividing the tile size
    assert pixel_block_for(torch.device("cuda"), 16, None) == (1, 1)  # one pixel per thread on CUDA
    assert pixel_block_for(cpu, 4, None) == (4, 4) and pixel_block_for(cpu, 8, None) == (4, 4)  # the CPU default
    assert pixel_block_for(cpu, 2, None) == (2, 2)
    # a tile of 6 or 18 px (divisible by 3, not 4) gets 2 px sides: a 3x3 block has no kernel
    assert pixel_block_for(cpu, 6, None) == (2, 2) and pixel_block_for(cpu, 18, None) == (2, 2)
    assert pixel_block_for(cpu, 9, None) == (1, 1) and pixel_block_for(cpu, 12, None) == (4, 4)
    with pytest.raises(ValueError, match="pixel block"):
        pixel_block_for(cpu, 16, (8, 4))  # 32 pixels per thread: not built


def test_cost_balanced_ranges_cover_the_tiles_in_order():
    """The first tile alone, then contiguous ranges of about equal cost that together cover every tile once."""
    from warpbags.wrapper import _cost_balanced_ranges

    costs = torch.tensor([5, 1, 1, 1, 100, 1, 1, 1, 1, 90, 1, 1])
    ranges = _cost_balanced_ranges(costs, 4, 2)
    assert ranges[0] == (0, 4)
    assert all(a[1] == b[0] for a, b in zip(ranges[:-1], ranges[1:])) and ranges[-1][1] == 12 * 4
    shares = [int(costs[a // 4:b // 4].sum()) for a, b in ranges[1:]]
    assert shares == [103, 96]  # the cut falls after the costly tile 4, where the running cost is nearest half
    assert _cost_balanced_ranges(torch.zeros(7), 2, 3) == [(0, 2), (2, 6), (6, 10), (10, 14)]  # no cost: even split
    assert _cost_balanced_ranges(torch.zeros(0), 2, 3) == []


def test_visits_per_tile_sums_each_tiles_pixels():
    """The backward's cost per tile: the list entries each pixel composited (its end minus its tile's start), summed
    over the tile's pixels, plus one; also for an image that is not a whole number of tiles."""
    from warpbags.wrapper import _tile_geometry, _visits_per_tile

    cams, height, width, size = 2, 7, 10, 4
    tiles = _tile_geometry(1, width, height, size)
    g = torch.Generator().manual_seed(0)
    offsets = torch.cat([torch.zeros(1), torch.randint(0, 9, (cams * tiles.tiles_x * tiles.tiles_y,), generator=g)])
    offsets = torch.cumsum(offsets, 0).to(torch.int32)
    ends = torch.zeros(cams, height, width, dtype=torch.int32)
    expected = torch.ones(len(offsets) - 1, dtype=torch.int64)
    for c in range(cams):
        for y in range(height):
            for x in range(width):
                tile = (c * tiles.tiles_y + y // size) * tiles.tiles_x + x // size
                start, stop = int(offsets[tile]), int(offsets[tile + 1])
                ends[c, y, x] = int(torch.randint(start, stop + 1, (1,), generator=g))
                expected[tile] += int(ends[c, y, x]) - start
    assert torch.equal(_visits_per_tile(offsets, ends, tiles), expected)


def test_gradients_do_not_depend_on_the_thread_schedule(monkeypatch):
    """Each range of tiles has its own gradient buffers, summed in range order: two threads taking the ranges in
    any order give the same gradients bit for bit as one thread walking them in turn."""
    import warpbags.wrapper as wrapper

    scene = random_scene(n=300, cams=2, width=40, height=36, seed=21, dtype=torch.float32)
    results = []
    for schedule in ("in turn", "reversed"):
        if schedule == "reversed":  # the threads' order made deterministic and as different as it gets
            monkeypatch.setattr(wrapper, "_run_ranges", lambda work, ranges, workers: [
                work(i, *ranges[i]) for i in [0, *reversed(range(1, len(ranges)))]])
        inputs = {k: v.detach().clone().requires_grad_(k in DIFFERENTIABLE) if isinstance(v, torch.Tensor) else v
                  for k, v in scene.items()}
        tensors = {k: v for k, v in inputs.items() if k in DIFFERENTIABLE}
        out, alpha, _ = warpbags.rasterization(**inputs, cpu_threads=2)
        (out * torch.linspace(0, 1, 3)).sum().backward()
        results.append((out.detach(), {k: v.grad for k, v in tensors.items()}))
    (out_a, grads_a), (out_b, grads_b) = results
    assert torch.equal(out_a, out_b)
    for name in grads_a:
        assert torch.equal(grads_a[name], grads_b[name]), name
