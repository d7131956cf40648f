"""Each rendering stage of warpbags/wrapper.py on its own, against its plain-torch float64 reference
(tests/reference.py): projection, spherical harmonics, tile binning and compositing.

For the differentiable stages: the float64 forward and backward (same cotangents) agree to rounding, a float64
`gradcheck` checks every differentiable input by finite differences, and float32 outputs and gradients are
compared with the float64 reference within stated tolerances. Binning is compared with a brute-force test of every
(tile, Gaussian) pair.
"""

from __future__ import annotations

import pytest
import torch
import warp as wp
from conftest import DEVICES, random_scene
from reference import (
    ALPHA_THRESHOLD,
    SH_C0,
    composite_reference,
    pixel_centers,
    projection_reference,
    sh_colors_reference,
    tiles_needed_reference,
    tiles_reached_reference,
)

from warpbags.wrapper import bin_gaussians, project_gaussians, rasterize_to_pixels, spherical_harmonics

PROJECTION_INPUTS = ("means", "quats", "scales", "opacities", "viewmats", "Ks")
F64 = torch.float64


def projection_scene(n=40, cams=2, width=29, height=23, seed=3):
    """`random_scene` (float64) plus Gaussians placed in camera 0's frame to reach every branch of the projection:
    two large ones beside the frustum (beyond the field-of-view clamp of the Jacobian, yet reaching into the
    image), one behind the camera (near plane), one nearly transparent (opacity below 1/255) and one small one
    beside the image (footprint off screen)."""
    scene = random_scene(n=n, cams=cams, width=width, height=height, seed=seed)
    K, viewmat = scene["Ks"][0], scene["viewmats"][0]
    fx, cx, fy, cy = K[0, 0], K[0, 2], K[1, 1], K[1, 2]
    lim_x = (width - cx) / fx + 0.3 * width / fx  # right edge of the clamp, in x/z
    lim_y = cy / fy + 0.3 * height / fy  # top edge, in -y/z
    z = 3.0
    camera_points = torch.tensor([
        [(lim_x + 0.1) * z, 0.0, z],  # beside the frustum (right), large
        [0.0, -(lim_y + 0.1) * z, z],  # beside the frustum (top), large
        [0.0, 0.0, -1.0],  # behind the camera
        [0.1, 0.1, z],  # nearly transparent
        [(lim_x + 0.5) * z, 0.0, z],  # small, beside the image
    ], dtype=F64)
    world = (camera_points - viewmat[:3, 3]) @ viewmat[:3, :3]  # R^T (p - t), row-wise
    g = torch.Generator().manual_seed(seed + 100)
    extra = dict(
        means=world,
        quats=torch.randn(5, 4, generator=g, dtype=F64),
        scales=torch.tensor([[0.6, 0.5, 0.4], [0.5, 0.6, 0.4], [0.1, 0.1, 0.1], [0.1, 0.1, 0.1], [0.01, 0.01, 0.01]],
                            dtype=F64),
        opacities=torch.tensor([0.8, 0.7, 0.9, 0.5 * ALPHA_THRESHOLD, 0.9], dtype=F64),
        colors=torch.rand(5, 3, generator=g, dtype=F64),
    )
    for name, values in extra.items():
        scene[name] = torch.cat([scene[name], values])
    return scene


def _projection_inputs(scene, dtype=F64, device="cpu"):
    return {name: scene[name].to(dtype=dtype, device=device).detach().clone().requires_grad_()
            for name in PROJECTION_INPUTS}


def _cotangents(outputs, seed=7):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(o.shape, generator=g, dtype=F64) for o in outputs]


def _backward(outputs, cotangents):
    sum((o * v.to(o)).sum() for o, v in zip(outputs, cotangents)).backward()


def _grad(leaf):
    """The leaf's gradient, zeros where autograd found it does not depend on it (e.g. the reference's opacities)."""
    return torch.zeros_like(leaf) if leaf.grad is None else leaf.grad


def test_projection_scene_reaches_every_branch():
    scene = projection_scene()
    means2d, _, _, radii, _ = projection_reference(*(scene[k] for k in PROJECTION_INPUTS), scene["width"],
                                                   scene["height"])
    n = scene["means"].shape[0]
    assert (radii[0, n - 5:n - 3] > 0).all(), "the two Gaussians beside the frustum reach the image"
    # beyond the clamp: x/z above (width - cx) / fx + 0.3 width / fx, i.e. the mean beyond 1.3 widths in pixels
    assert means2d[0, n - 5, 0] > 1.3 * scene["width"] and means2d[0, n - 4, 1] < -0.3 * scene["height"]
    assert (radii[0, n - 3:] == 0).all(), "behind, transparent and off-screen Gaussians are culled"
    assert (radii[:, : n - 5] > 0).float().mean() > 0.9


@pytest.mark.parametrize("device", DEVICES)
def test_projection_matches_reference_float64(device):
    """Forward within 1e-12 of each output's largest, radii exactly; gradients within 1e-12 of each input's largest
    (measured: 3.2e-16 and 7.8e-16)."""
    scene = projection_scene()
    width, height = scene["width"], scene["height"]
    ours_in, ref_in = _projection_inputs(scene, device=device), _projection_inputs(scene)
    ours = project_gaussians(*ours_in.values(), width, height)
    *ref, extents = projection_reference(*ref_in.values(), width, height)
    for name, a, b in zip(("means2d", "conics", "depths"), ours[:3], ref[:3]):
        torch.testing.assert_close(a.cpu(), b, rtol=0, atol=1e-12 * b.abs().max().item(), msg=lambda m: f"{name}: {m}")
    assert torch.equal(ours[3].cpu(), ref[3])

    cotangents = _cotangents(ours[:3])
    _backward(ours[:3], cotangents)
    _backward(ref[:3], cotangents)
    for name in PROJECTION_INPUTS:
        expected = _grad(ref_in[name])
        torch.testing.assert_close(_grad(ours_in[name]).cpu(), expected, rtol=0, atol=1e-12 * expected.abs().max().item(),
                                   msg=lambda m: f"{name}: {m}")
    assert ours_in["opacities"].grad is None  # opacity only culls and sizes the (integer) radius


def test_projection_gradcheck_float64():
    """Finite differences through every input, including the clamped Jacobian of the Gaussians beside the frustum."""
    scene = projection_scene(n=6, cams=2, width=14, height=11, seed=5)
    inputs = _projection_inputs(scene)
    radii = project_gaussians(*inputs.values(), scene["width"], scene["height"])[3]
    assert (radii[0, -5:-3] > 0).all() and (radii[:, :6] > 0).all()

    def project(*args):
        return project_gaussians(*args, scene["width"], scene["height"])[:3]

    assert torch.autograd.gradcheck(project, tuple(inputs.values()), eps=1e-6, atol=1e-7, rtol=1e-6)


def test_the_jacobian_is_clamped_at_1_6_times_the_half_field_of_view():
    """The Jacobian is taken at x/z clamped to 1.6 tan(fov / 2), wider than 3DGS's 1.3 (`tangent_limits` says what
    the narrower clamp measured); the expected covariance is written out here, not taken from the reference."""
    width, height, f, z, sigma = 100, 80, 100.0, 3.0, 0.6  # large enough to reach into the image
    tan_half = width / 2 / f
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=F64)[None]
    for ratio, clamped in ((1.45, 1.45), (1.75, 1.6)):  # inside the clamp, and beyond it
        x = ratio * tan_half * z
        means, quats = torch.tensor([[x, 0.0, z]], dtype=F64), torch.tensor([[1.0, 0, 0, 0]], dtype=F64)
        scales, opacities = sigma * torch.ones(1, 3, dtype=F64), torch.ones(1, dtype=F64)
        _, conics, _, radii = project_gaussians(means, quats, scales, opacities, torch.eye(4, dtype=F64)[None], K,
                                                width, height)
        assert radii[0, 0] > 0
        tx = clamped * tan_half * z
        jacobian = torch.tensor([[f / z, 0, -f * tx / z**2], [0, f / z, 0]], dtype=F64)
        cov2d = sigma**2 * jacobian @ jacobian.T + 0.3 * torch.eye(2, dtype=F64)
        inverse = torch.linalg.inv(cov2d)
        torch.testing.assert_close(conics[0, 0], torch.stack([inverse[0, 0], inverse[0, 1], inverse[1, 1]]),
                                   rtol=1e-12, atol=0)


def _clamps_reached(scene):
    """{(axis, side)} of the Jacobian clamps that some unculled (camera, Gaussian) pair of `scene` reaches."""
    width, height = scene["width"], scene["height"]
    radii = project_gaussians(*(scene[k] for k in PROJECTION_INPUTS), width, height)[3]
    rot, trans, K = scene["viewmats"][:, None, :3, :3], scene["viewmats"][:, None, :3, 3], scene["Ks"][:, None]
    p = (rot @ scene["means"][None, :, :, None])[..., 0] + trans
    reached = set()
    for axis, size in ((0, width), (1, height)):
        f, c = K[..., axis, axis], K[..., axis, 2]
        ratio = p[..., axis] / p[..., 2]
        if ((ratio > (size - c) / f + 0.3 * size / f) & (radii > 0)).any():
            reached.add((axis, "upper"))
        if ((ratio < -(c / f + 0.3 * size / f)) & (radii > 0)).any():
            reached.add((axis, "lower"))
    return reached


def _launch_warp_adjoint(kernel, dim, arguments: dict, adjoints: dict) -> None:
    """Launch the Warp-generated adjoint of `kernel` on the CPU: `arguments` by parameter name as for the forward
    launch, `adjoints` (parameter name -> adjoint array; absent names get none) accumulating the inputs' gradients."""
    import warpbags.wrapper as wrapper

    values = wrapper._ordered_arguments(kernel, arguments)
    names = wrapper._parameter_names(kernel)
    wp.launch(wrapper._overload(kernel, values), dim=dim, inputs=values,
              adj_inputs=[adjoints.get(name) for name in names], adjoint=True, device="cpu", record_tape=False)


def _warp_adjoint_of_projection(inputs, width, height, cotangents):
    """The inputs' gradients by Warp's generated adjoint of the forward kernel (what the projection ran before its
    hand-written backward), one launch over every pair."""
    import warpbags.wrapper as wrapper

    stage, cpu = wrapper._PROJECTION, torch.device("cpu")
    cams, n = inputs["viewmats"].shape[0], inputs["means"].shape[0]
    dtype = inputs["means"].dtype
    grads = {name: torch.zeros_like(inputs[name]) for name in PROJECTION_INPUTS}
    outputs = [wrapper._output_tensor(kind, (cams, n), dtype, cpu) for kind in stage.outputs.values()]
    arguments = wrapper._stage_arguments(stage, [*inputs.values(), width, height, 0.01, 1e10, 0.3], outputs, None,
                                         dtype, [*grads.values(), None, None, None, None, None])
    # the adjoint of a store clears its output's adjoint: Warp gets copies of the cotangents
    adjoints = {name: arguments[name].grad for name in PROJECTION_INPUTS}
    adjoints.update((name, wrapper._to_warp(v.clone(), stage.outputs[name])) for name, v in cotangents.items())
    _launch_warp_adjoint(stage.kernel, (cams, n), arguments, adjoints)
    return grads


# Measured largest differences, of each input's largest gradient: float64 5.7e-16, float32 5.9e-7.
@pytest.mark.parametrize("dtype,tol", [(F64, 1e-12), (torch.float32, 3e-6)])
def test_projection_backward_kernel_equals_warp_adjoint(dtype, tol):
    """The hand-written backward kernel against Warp's generated adjoint of the forward kernel, with random
    cotangents on every pair, culled ones included: gradients within `tol` of each input's largest. The scene has
    culled Gaussians and Gaussians beyond each of the four clamps of the Jacobian (one more below camera 0's image
    for the fourth)."""
    scene = projection_scene(n=60, cams=3, seed=2)
    K, viewmat, height = scene["Ks"][0], scene["viewmats"][0], scene["height"]
    below = ((1.3 * height - K[1, 2]) / K[1, 1] + 0.1) * 3.0  # y beyond the lower image edge's clamp, at z = 3
    extra = dict(means=(torch.tensor([[0.0, below, 3.0]], dtype=F64) - viewmat[:3, 3]) @ viewmat[:3, :3],
                 quats=torch.tensor([[0.9, 0.2, -0.3, 0.1]], dtype=F64),
                 scales=torch.tensor([[0.5, 0.6, 0.4]], dtype=F64), opacities=torch.tensor([0.8], dtype=F64))
    for name, values in extra.items():
        scene[name] = torch.cat([scene[name], values])
    assert len(_clamps_reached(scene)) == 4

    inputs = _projection_inputs(scene, dtype)
    width, height = scene["width"], scene["height"]
    outputs = project_gaussians(*inputs.values(), width, height)
    assert (outputs[3] == 0).sum() >= 6, "culled pairs"
    cotangents = dict(zip(("means2d", "conics", "depths"), (v.to(dtype) for v in _cotangents(outputs[:3]))))
    _backward(outputs[:3], cotangents.values())
    expected = _warp_adjoint_of_projection({k: v.detach() for k, v in inputs.items()}, width, height, cotangents)
    assert expected["opacities"].abs().max() == 0 and inputs["opacities"].grad is None
    for name in PROJECTION_INPUTS:
        torch.testing.assert_close(_grad(inputs[name]), expected[name], rtol=0,
                                   atol=tol * expected[name].abs().max().item(), msg=lambda m: f"{name}: {m}")


def test_projection_culls_an_opacity_of_exactly_the_cut_off():
    """At an opacity of exactly 1/255 the footprint's extent is 0: radius 0, and culled as every radius 0 is (float
    outputs zero, no gradient), which the backward kernel relies on. (Warp's generated adjoint gave NaN there, for
    every input: it differentiates the extent's square root at 0.)"""
    scene = projection_scene()
    width, height = scene["width"], scene["height"]
    assert (project_gaussians(*(scene[k] for k in PROJECTION_INPUTS), width, height)[3][:, :4] > 0).all()
    scene["opacities"][:4] = ALPHA_THRESHOLD
    inputs = _projection_inputs(scene)
    outputs = project_gaussians(*inputs.values(), width, height)
    assert torch.equal(outputs[3], projection_reference(*(scene[k] for k in PROJECTION_INPUTS), width, height)[3])
    assert (outputs[3][:, :4] == 0).all() and all((o[:, :4] == 0).all() for o in outputs[:3])
    _backward(outputs[:3], _cotangents(outputs[:3]))
    assert all((inputs[name].grad[:4] == 0).all() for name in ("means", "quats", "scales"))
    assert all(inputs[name].grad.isfinite().all() for name in ("viewmats", "Ks"))


def test_projection_float32_against_float64_reference():
    """float32 means2d within 5e-5 px, depths within 1e-6 relative, conics within 3e-6 of the largest; radii equal
    except where the reference's extent is within 1e-3 of an integer (rounding up may then differ by one); gradients
    within 3e-6 of each input's largest (measured: 4.4e-6 px, 7.9e-8, 2.4e-7; no radius off, the closest extent
    3.8e-3 from an integer; gradients 3.2e-7)."""
    scene = projection_scene()
    width, height = scene["width"], scene["height"]
    ours_in, ref_in = _projection_inputs(scene, torch.float32), _projection_inputs(scene)
    ours = project_gaussians(*ours_in.values(), width, height)
    *ref, extents = projection_reference(*ref_in.values(), width, height)
    valid = ref[3] > 0
    assert torch.equal(ours[3] > 0, valid), "the same Gaussians are culled"
    torch.testing.assert_close(ours[0].double(), ref[0], rtol=0, atol=5e-5)
    torch.testing.assert_close(ours[1].double(), ref[1], rtol=0, atol=3e-6 * ref[1].abs().max().item())
    torch.testing.assert_close(ours[2].double(), ref[2], rtol=1e-6, atol=0)
    off = ours[3] != ref[3]
    near_integer = (extents - extents.round()).abs() < 1e-3
    assert (~off | near_integer).all() and ((ours[3] - ref[3]).abs() <= 1).all()

    cotangents = _cotangents(ours[:3])
    _backward(ours[:3], cotangents)
    _backward(ref[:3], cotangents)
    for name in PROJECTION_INPUTS:
        expected = _grad(ref_in[name])
        torch.testing.assert_close(_grad(ours_in[name]).double(), expected, rtol=0,
                                   atol=3e-6 * expected.abs().max().item(), msg=lambda m: f"{name}: {m}")


def _sh_inputs(degree, dtype=F64, device="cpu", seed=2, n=30, cams=3):
    scene = random_scene(n=n, cams=cams, sh_degree=3, seed=seed)  # K = 16 coefficients for every degree
    return {name: scene[name].to(dtype=dtype, device=device).detach().clone().requires_grad_()
            for name in ("means", "colors", "viewmats")}


def _sh_against_reference(degree: int, dtype: torch.dtype, device: str, value_atol: float, grad_atol: float):
    """Colours within `value_atol` of the float64 reference, gradients within `grad_atol` of each input's largest;
    returns our inputs (with their gradients)."""
    ours_in, ref_in = _sh_inputs(degree, dtype, device=device), _sh_inputs(degree)
    ours = spherical_harmonics(ours_in["means"], ours_in["colors"], ours_in["viewmats"], degree)
    ref = sh_colors_reference(ref_in["means"], ref_in["colors"], ref_in["viewmats"], degree)
    torch.testing.assert_close(ours.cpu().double(), ref, rtol=0, atol=value_atol)
    assert (ref == 0).float().mean() < 0.2, "mostly unclamped colours"
    cotangents = _cotangents([ours])
    _backward([ours], cotangents)
    _backward([ref], cotangents)
    for name in ref_in:
        expected = _grad(ref_in[name])
        torch.testing.assert_close(_grad(ours_in[name]).cpu().double(), expected, rtol=0,
                                   atol=grad_atol * expected.abs().max().item(), msg=lambda m: f"{name}: {m}")
    return ours_in


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_matches_reference_float64(degree, device):
    """Colours within 1e-12, gradients within 1e-12 of each input's largest (measured: 3.3e-16 and 9e-16);
    coefficients above the degree get none."""
    ours_in = _sh_against_reference(degree, torch.float64, device, 1e-12, 1e-12)
    assert (ours_in["colors"].grad[:, (degree + 1) ** 2:] == 0).all()


def test_sh_gradcheck_float64():
    """Finite differences through every input, of the hand-written backward kernel."""
    inputs = _sh_inputs(3, n=5, cams=2)
    assert type(spherical_harmonics(*inputs.values(), 3).grad_fn).__name__ == "_SHColorsBackward"
    assert torch.autograd.gradcheck(lambda *args: spherical_harmonics(*args, 3), tuple(inputs.values()), eps=1e-6,
                                    atol=1e-7, rtol=1e-6)


def test_sh_builds_an_autograd_node_only_for_gradients():
    """No node (nor backward) without torch gradients or with no input requiring one; with the coefficients alone
    requiring one, only they get a gradient."""
    inputs = {name: t.detach() for name, t in _sh_inputs(2).items()}
    with torch.no_grad():
        assert spherical_harmonics(*(t.clone().requires_grad_() for t in inputs.values()), 2).grad_fn is None
    assert spherical_harmonics(*inputs.values(), 2).grad_fn is None
    coeffs = inputs["colors"].clone().requires_grad_()
    colors = spherical_harmonics(inputs["means"], coeffs, inputs["viewmats"], 2)
    assert type(colors.grad_fn).__name__ == "_SHColorsBackward"
    colors.sum().backward()
    assert coeffs.grad is not None and (coeffs.grad[:, 9:] == 0).all() and (coeffs.grad[:, :9] != 0).any()


def test_sh_float32_against_float64_reference():
    """float32 colours within 2e-6 and gradients within 4e-6 of each input's largest (measured: 1.7e-7, 4e-7)."""
    _sh_against_reference(3, torch.float32, "cpu", 2e-6, 4e-6)


SH_INPUTS = ("means", "coeffs", "viewmats")


def _sh_tie(dtype):
    """A DC coefficient c with C0 c + 0.5 == 0 exactly in `dtype` (each step rounded, as the kernel computes it): at
    degree 0 the clamp max(rgb + 0.5, 0) is at its tie."""
    c0 = torch.tensor(SH_C0, dtype=dtype)
    value = torch.tensor(-0.5, dtype=dtype) / c0
    for _ in range(16):
        if c0 * value + 0.5 == 0:
            return value.item()
        value = torch.nextafter(value, torch.tensor(0.0, dtype=dtype))
    raise AssertionError(f"no tie near -0.5 / C0 in {dtype}")


def _clamped_sh_inputs(dtype):
    """`_sh_inputs` (3 cameras, 30 Gaussians, 16 coefficients) with colours clamped at 0: Gaussian 0 in every channel
    and camera, Gaussian 1 in its green channel, Gaussian 2 at the clamp's tie at degree 0 (and on either side of it
    by camera at higher degrees)."""
    scene = random_scene(n=30, cams=3, sh_degree=3, seed=2)
    scene["colors"][0, 0] = -6.0
    scene["colors"][1, 0, 1] = -6.0
    scene["colors"][2, 0] = _sh_tie(dtype)
    return {name: scene[key].to(dtype).detach().clone().requires_grad_()
            for name, key in zip(SH_INPUTS, ("means", "colors", "viewmats"))}


def _warp_adjoint_of_sh(inputs, degree, cotangent):
    """The inputs' gradients by Warp's generated adjoint of the forward kernel (what the SH stage ran before its
    hand-written backward), one launch over every pair."""
    import warpbags.wrapper as wrapper

    stage, cpu = wrapper._SH_COLORS, torch.device("cpu")
    cams, n = inputs["viewmats"].shape[0], inputs["means"].shape[0]
    dtype = inputs["means"].dtype
    grads = {name: torch.zeros_like(inputs[name]) for name in SH_INPUTS}
    outputs = [wrapper._output_tensor("vec3", (cams, n), dtype, cpu)]
    arguments = wrapper._stage_arguments(stage, [*inputs.values(), degree], outputs, None, dtype,
                                         [*grads.values(), None])
    # the adjoint of a store clears its output's adjoint: Warp gets a copy of the cotangent
    adjoints = {name: arguments[name].grad for name in SH_INPUTS}
    adjoints["colors"] = wrapper._to_warp(cotangent.clone(), "vec3")
    _launch_warp_adjoint(stage.kernel, (cams, n), arguments, adjoints)
    return grads


# Measured largest differences, of each input's largest gradient: float64 5.8e-16, float32 2.1e-7 (the coefficients
# bit for bit).
@pytest.mark.parametrize("dtype,tol", [(F64, 1e-12), (torch.float32, 2e-6)])
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_backward_kernel_equals_warp_adjoint(degree, dtype, tol):
    """The hand-written backward kernel against Warp's generated adjoint of the forward kernel, with random
    cotangents on every pair: gradients within `tol` of each input's largest. Clamped channels pass no gradient, at
    the clamp's tie neither (Warp's adjoint of max(rgb + 0.5, 0) gives a tie to the 0); coefficients above the
    degree get exactly none, and at degree 0 neither do the means and view matrices."""
    inputs = _clamped_sh_inputs(dtype)
    colors = spherical_harmonics(*inputs.values(), degree)
    assert (colors[:, 0] == 0).all() and (colors[:, 1, 1] == 0).all() and (colors[:, 1] > 0).sum() == 6
    if degree == 0:
        assert (colors[:, 2] == 0).all(), "at the tie"
    else:
        assert 0 < (colors[:, 2] == 0).sum() < 9, "clamped by some cameras, not all"
    cotangent = torch.randn(colors.shape, generator=torch.Generator().manual_seed(7), dtype=F64).to(dtype)
    colors.backward(cotangent)
    expected = _warp_adjoint_of_sh({k: v.detach() for k, v in inputs.items()}, degree, cotangent)
    for name in SH_INPUTS:
        torch.testing.assert_close(inputs[name].grad, expected[name], rtol=0,
                                   atol=tol * expected[name].abs().max().item(), msg=lambda m: f"{name}: {m}")
    for grads in (inputs["coeffs"].grad, expected["coeffs"]):
        assert (grads[0] == 0).all() and (grads[1, :, 1] == 0).all() and (grads[1, :, 0] != 0).any()
        assert (grads[:, (degree + 1) ** 2:] == 0).all() and (grads[:, : (degree + 1) ** 2] != 0).any()
        if degree == 0:
            assert (grads[2] == 0).all()
    if degree == 0:
        assert all((inputs[name].grad == 0).all() and (expected[name] == 0).all() for name in ("means", "viewmats"))


def _listed(bins, cams, n):
    """([C, tiles_y, tiles_x, N] bool of the (tile, Gaussian) pairs `bins` lists, every tile's list of flat ids
    cam * N + n); checks that a tile lists only its own camera's Gaussians, each once."""
    listed = torch.zeros(cams, bins.tiles_y * bins.tiles_x, n, dtype=torch.bool)
    tiles_per_camera = bins.tiles_y * bins.tiles_x
    lists = []
    for tile in range(cams * tiles_per_camera):
        ids = bins.isect_ids[bins.tile_offsets[tile]:bins.tile_offsets[tile + 1]].long()
        cam = tile // tiles_per_camera
        assert (ids // n == cam).all(), f"tile {tile} lists another camera's Gaussians"
        assert len(set(ids.tolist())) == len(ids), f"tile {tile} lists a Gaussian twice"
        listed[cam, tile % tiles_per_camera, ids % n] = True
        lists.append(ids)
    return listed.reshape(cams, bins.tiles_y, bins.tiles_x, n), lists


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("tile_size", [4, 8, 16])
def test_binning_matches_brute_force_per_tile(dtype, tile_size):
    """The lists hold the pairs whose reach meets the tile's rectangle of pixel centres, up to a margin: every pair
    reached is listed (so every pair where a pixel centre gets alpha >= 1/255, what the rasterizer needs), and every
    listed pair is reached once sigma's bound is widened by 2e-3 (the kernel's stated margin of 1e-3 for float32
    rounding, and as much again; measured: 5e-4 needed on seed 1, none on seeds 2 and 9). Each tile's list runs
    front to back. 29 x 23 pixels: the last tile row and column are cut by the image edge."""
    scene = projection_scene(n=120, cams=2, seed=9)
    width, height = scene["width"], scene["height"]
    inputs = {name: scene[name].to(dtype) for name in PROJECTION_INPUTS}
    means2d, conics, depths, radii = project_gaussians(*inputs.values(), width, height)
    bins = bin_gaussians(means2d, conics, inputs["opacities"], radii, depths, width, height, tile_size)
    cams, n = radii.shape
    listed, lists = _listed(bins, cams, n)

    as64 = (means2d.double(), conics.double(), inputs["opacities"].double(), radii, width, height, tile_size)
    needed = tiles_needed_reference(*as64)
    reached = tiles_reached_reference(*as64)
    assert needed.sum() > 3 * needed[..., 0].numel(), "several Gaussians per tile"
    assert not (needed & ~reached).any()  # the reference's own consistency: pixel centres lie in the rectangles
    assert not (needed & ~listed).any(), f"{int((needed & ~listed).sum())} needed pairs not listed"
    assert not (reached & ~listed).any(), f"{int((reached & ~listed).sum())} reached pairs not listed"
    widened = tiles_reached_reference(*as64, slack=2e-3)
    assert not (listed & ~widened).any(), f"{int((listed & ~widened).sum())} listed pairs out of reach"
    flat_depths = depths.reshape(-1)
    for ids in lists:
        assert (flat_depths[ids].diff() >= 0).all(), "front to back"


def test_binning_breaks_depth_ties_by_index_in_every_precision():
    """Gaussians at equal depths are listed in index order, whichever sort puts them front to back (float32: Warp's
    radix sort of (depth, index) pairs; float64: torch's stable argsort): with depths rounded to a few values,
    the float32 and float64 lists are the same, and each tie runs in increasing index."""
    scene = projection_scene(n=120, cams=2, seed=9)
    width, height = scene["width"], scene["height"]
    means2d, conics, depths, radii = project_gaussians(*(scene[name] for name in PROJECTION_INPUTS), width, height)
    tied = depths.round()  # a handful of depth values for 120 Gaussians
    assert len(tied.unique()) < 10
    lists = [bin_gaussians(means2d.to(dtype), conics.to(dtype), scene["opacities"].to(dtype), radii, tied.to(dtype),
                           width, height, 8) for dtype in (torch.float32, torch.float64)]
    assert torch.equal(lists[0].tile_offsets, lists[1].tile_offsets)
    assert torch.equal(lists[0].isect_ids, lists[1].isect_ids)
    _, per_tile = _listed(lists[0], *radii.shape)
    flat_depths = tied.reshape(-1)
    for ids in per_tile:
        same_depth = flat_depths[ids].diff() == 0
        assert (ids.diff()[same_depth] > 0).all(), "ties in index order"


def test_binning_lists_no_tile_reached_only_beyond_the_image():
    """A unit-covariance Gaussian (reach 3.3 px) centred 2 px right of a 29 px wide image, and one 2 px below a 23 px
    high one: each reaches one tile of 8 px through pixel centres inside the image, and is listed there alone."""
    width, height = 29, 23
    means2d = torch.tensor([[[31.0, 10.0], [10.0, 25.0]]], dtype=F64)
    conics = torch.tensor([[[1.0, 0.0, 1.0], [1.0, 0.0, 1.0]]], dtype=F64)
    opacities, radii = torch.tensor([0.9, 0.9], dtype=F64), torch.tensor([[4, 4]], dtype=torch.int32)
    bins = bin_gaussians(means2d, conics, opacities, radii, torch.ones(1, 2, dtype=F64), width, height, 8)
    listed, _ = _listed(bins, 1, 2)
    reached = tiles_reached_reference(means2d, conics, opacities, radii, width, height, 8)
    assert reached[0, :, :, 0].nonzero().tolist() == [[1, 3]] and reached[0, :, :, 1].nonzero().tolist() == [[2, 1]]
    assert torch.equal(listed, reached)


def _composite_inputs(dtype=F64, n=40, width=26, height=19, seed=6):
    scene = random_scene(n=n, cams=2, width=width, height=height, seed=seed)
    with torch.no_grad():
        means2d, conics, depths, radii = project_gaussians(*(scene[k] for k in PROJECTION_INPUTS), width, height)
    leaves = dict(means2d=means2d, conics=conics, colors=scene["colors"].expand(2, -1, -1), opacities=scene["opacities"],
                  depths=depths)
    return {k: v.to(dtype).contiguous().requires_grad_() for k, v in leaves.items()}, radii, width, height


def _composite_reference(leaves, radii, width, height):
    """`composite_reference` per camera, Gaussians depth-sorted: [C, H, W] colours (3), depths and alphas."""
    outputs = []
    pixels = pixel_centers(width, height)
    for cam in range(radii.shape[0]):
        order = torch.argsort(leaves["depths"][cam].detach())
        conics = leaves["conics"][cam, order]
        projected = (leaves["means2d"][cam, order], conics[:, 0], conics[:, 1], conics[:, 2],
                     leaves["opacities"][order], leaves["colors"][cam, order], leaves["depths"][cam, order],
                     radii[cam, order] > 0)
        rgb, depth, alpha = composite_reference(projected, pixels)
        outputs.append((rgb.reshape(height, width, 3), depth.reshape(height, width), alpha.reshape(height, width)))
    return [torch.stack(parts) for parts in zip(*outputs)]


def _composite(leaves, radii, width, height, tile_size=4):
    bins = bin_gaussians(leaves["means2d"], leaves["conics"], leaves["opacities"], radii, leaves["depths"], width,
                         height, tile_size)
    return rasterize_to_pixels(*leaves.values(), bins, width, height)


# Measured largest errors: float64 4.2e-16 (values, of max(1, largest)) and 8.4e-16 (gradients, of each input's
# largest); float32 2.0e-7 and 1.6e-7.
@pytest.mark.parametrize("dtype,value_tol,grad_tol", [(F64, 1e-12, 1e-12), (torch.float32, 2e-6, 2e-6)])
def test_compositing_matches_reference(dtype, value_tol, grad_tol):
    """The rasterizer stage alone, given the same projected Gaussians: colours, depths and alphas within
    `value_tol` of max(1, their largest), gradients within `grad_tol` of each input's largest."""
    ours_in, radii, width, height = _composite_inputs(dtype)
    ref_in = {k: v.detach().double().requires_grad_() for k, v in ours_in.items()}
    ours = _composite(ours_in, radii, width, height)
    ref = _composite_reference(ref_in, radii, width, height)
    assert ref[2].max() > 0.5
    for name, a, b in zip(("colors", "depths", "alphas"), ours, ref):
        torch.testing.assert_close(a.double(), b, rtol=0, atol=value_tol * max(b.abs().max().item(), 1.0),
                                   msg=lambda m: f"{name}: {m}")
    cotangents = _cotangents(ours)
    _backward(ours, cotangents)
    _backward(ref, cotangents)
    for name in ref_in:
        expected = _grad(ref_in[name])
        torch.testing.assert_close(_grad(ours_in[name]).double(), expected, rtol=0,
                                   atol=grad_tol * expected.abs().max().item(), msg=lambda m: f"{name}: {m}")


def test_compositing_gradcheck_float64():
    leaves, radii, width, height = _composite_inputs(n=8, width=10, height=9, seed=11)
    bins = bin_gaussians(leaves["means2d"], leaves["conics"], leaves["opacities"], radii, leaves["depths"], width,
                         height, 4)

    def composite(*args):
        return rasterize_to_pixels(*args, bins, width, height)

    assert torch.autograd.gradcheck(composite, tuple(leaves.values()), eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)


def test_a_host_thread_limit_reaches_every_stage_given_no_count(monkeypatch):
    """`limited_host_threads` (a Ray task's CPUs) caps the stages that name no thread count, a limit inside another
    never raises it and each restores the one around it, and without a limit they take every usable core."""
    import warpbags.threads as threads
    import warpbags.wrapper as wrapper

    monkeypatch.setattr(threads, "usable_cores", lambda: 8)  # a machine larger than the limits
    big = (4, 10 ** 6)
    assert wrapper._default_cpu_threads() == 8
    with threads.limited_host_threads(3):
        assert wrapper._default_cpu_threads() == 3
        assert len(wrapper._GaussianRanges.of(wrapper._PROJECTION, big, torch.device("cpu")).ranges) == 3 + 1
        with threads.limited_host_threads(1):
            assert wrapper._GaussianRanges.of(wrapper._PROJECTION, big, torch.device("cpu")).ranges is None
        with threads.limited_host_threads(None), threads.limited_host_threads(6):
            assert wrapper._default_cpu_threads() == 3
        assert wrapper._default_cpu_threads() == 3
    assert wrapper._default_cpu_threads() == 8


@pytest.mark.parametrize("cores", [2, 3])
def test_projection_and_sh_over_gaussian_ranges_match_one_launch(cores, monkeypatch):
    """On the CPU the projection and SH stages run forward and backward in ranges of Gaussians on the host threads:
    outputs and per-Gaussian gradients bit for bit those of one launch over everything (each Gaussian's cameras
    are summed in the same order), the per-camera gradients (viewmats, Ks) equal up to the rounding of their
    per-range sums."""
    import warpbags.wrapper as wrapper

    scene = projection_scene(n=53, cams=3)
    n = scene["means"].shape[0]
    coeffs = 0.3 * torch.randn(n, 9, 3, generator=torch.Generator().manual_seed(4), dtype=F64)
    results = {}
    monkeypatch.setattr(wrapper, "MIN_PAIRS_PER_THREAD", 1)  # cut however small the scene
    for threads in (1, cores):
        monkeypatch.setattr(wrapper, "_default_cpu_threads", lambda: threads)
        leaves = {k: scene[k].detach().clone().requires_grad_() for k in PROJECTION_INPUTS}
        sh_coeffs = coeffs.clone().requires_grad_()
        means2d, conics, depths, radii = project_gaussians(*(leaves[k] for k in PROJECTION_INPUTS), 29, 23)
        colors = spherical_harmonics(leaves["means"], sh_coeffs, leaves["viewmats"], 2)
        outputs = (means2d, conics, depths, colors)
        g = torch.Generator().manual_seed(9)
        sum((o * torch.randn(o.shape, generator=g, dtype=F64)).sum() for o in outputs).backward()
        results[threads] = ([o.detach() for o in (*outputs, radii)],
                            {**{k: v.grad for k, v in leaves.items()}, "coeffs": sh_coeffs.grad})
    assert len(wrapper._GaussianRanges.of(wrapper._PROJECTION, (3, n), torch.device("cpu")).ranges) == cores + 1
    (one_out, one_grads), (cut_out, cut_grads) = results[1], results[cores]
    assert all(torch.equal(a, b) for a, b in zip(one_out, cut_out))
    for name in ("means", "quats", "scales", "coeffs"):  # the opacities get none
        assert torch.equal(one_grads[name], cut_grads[name]), name
    for name in ("viewmats", "Ks"):
        assert not torch.equal(cut_grads[name], torch.zeros_like(cut_grads[name]))
        torch.testing.assert_close(cut_grads[name], one_grads[name], rtol=1e-12, atol=1e-12,
                                   msg=lambda m: f"{name}: {m}")
