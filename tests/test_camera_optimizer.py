"""The camera optimizer: both parameterizations (float64 gradients against finite differences, what each parameter
does to the image), the CamP preconditioner, sparse per-camera steps, the gauge, and AOT CUDA code for the kernels."""

from __future__ import annotations

import io
import math

import pytest
import torch
import warp as wp
from conftest import look_at

from warpbags.camera_optimizer import (CameraOptimizer, CameraOptimizerSettings, corrected_viewmats, hypothesis_turns,
                                       preconditioner)
from warpbags.camera_setup import training_cameras
from warpbags.cameras import camera_centers, mean_viewmats, project_points
from warpbags.configs.train import load_preset
from warpbags.errors import WarpbagsError
from warpbags.lie import se3_exp
from warpbags.wrapper import apply_object_deltas

F64 = torch.float64


def orbit_cameras(count: int = 3, radius: float = 4.0, dtype=F64) -> tuple[torch.Tensor, torch.Tensor]:
    """[C,4,4] cameras on a circle looking at (0.1, -0.2, 0.05) and their [C,3,3] intrinsics (64 px, 30 deg fov)."""
    target = torch.tensor([0.1, -0.2, 0.05], dtype=dtype)
    viewmats = torch.stack([look_at(torch.tensor([radius * math.cos(a), radius * math.sin(a), 0.7], dtype=dtype), target)
                            for a in torch.linspace(0, 2 * math.pi, count + 1)[:-1].tolist()])
    focal = 32 / math.tan(math.radians(15))
    K = torch.tensor([[focal, 0, 32], [0, focal, 32], [0, 0, 1]], dtype=dtype)
    return viewmats, K.expand(count, 3, 3).contiguous()


@pytest.mark.parametrize("parameterization", ["camera", "object"])
def test_pose_transform_gradients_match_finite_differences(parameterization):
    viewmats, _ = orbit_cameras()
    centers = torch.tensor([[0.1, -0.2, 0.05]], dtype=F64).expand(3, 3).contiguous()
    generator = torch.Generator().manual_seed(0)
    for scale in (0.0, 0.05, 0.4):  # at zero (where every camera starts), small and large corrections
        params = (scale * torch.randn(3, 6, generator=generator, dtype=F64)).requires_grad_()
        inputs = (params,) if parameterization == "camera" else (params, centers.clone().requires_grad_())
        function = (lambda p: corrected_viewmats("camera", viewmats, p)) if parameterization == "camera" else (
            lambda p, c: apply_object_deltas(viewmats, p, c))
        assert torch.autograd.gradcheck(function, inputs, eps=1e-6, atol=1e-8, rtol=1e-6)


def test_object_parameters_act_on_the_object_image_as_documented():
    viewmats, Ks = orbit_cameras(count=1)
    center = torch.tensor([[0.1, -0.2, 0.05]], dtype=F64)
    before, depth = project_points(viewmats, Ks, center)
    zero = corrected_viewmats("object", viewmats, torch.zeros(1, 6, dtype=F64), center)
    torch.testing.assert_close(zero, viewmats, rtol=0, atol=1e-12)
    # A rotation about the object centre leaves the centre's image where it was.
    turned = corrected_viewmats("object", viewmats, torch.tensor([[0.2, -0.1, 0.3, 0, 0, 0]], dtype=F64), center)
    after, turned_depth = project_points(turned, Ks, center)
    torch.testing.assert_close(after, before, rtol=0, atol=1e-9)
    torch.testing.assert_close(turned_depth, depth, rtol=0, atol=1e-12)
    # u shifts the centre's image by u focal lengths; s scales its depth by e^s.
    moved = corrected_viewmats("object", viewmats, torch.tensor([[0, 0, 0, 0.01, -0.02, 0.1]], dtype=F64), center)
    after, moved_depth = project_points(moved, Ks, center)
    focal = Ks[0, 0, 0]
    torch.testing.assert_close(after - before, torch.tensor([[[0.01, -0.02]]], dtype=F64) * focal, rtol=0, atol=1e-9)
    torch.testing.assert_close(moved_depth, depth * math.exp(0.1), rtol=1e-12, atol=0)
    # Rigid: the result is still a rotation plus translation.
    rotation = moved[0, :3, :3]
    torch.testing.assert_close(rotation @ rotation.T, torch.eye(3, dtype=F64), rtol=0, atol=1e-12)


def test_camera_parameterization_is_the_left_se3_exponential():
    viewmats, _ = orbit_cameras()
    deltas = 0.3 * torch.randn(3, 6, generator=torch.Generator().manual_seed(1), dtype=F64)
    torch.testing.assert_close(corrected_viewmats("camera", viewmats, deltas), se3_exp(deltas) @ viewmats,
                               rtol=0, atol=1e-12)


def _latent_moments(parameterization, viewmats, Ks, points, centers, matrix, size=64):
    """J^T J / n of the projected points (in image sizes of `size` px) against latent parameters mapped by `matrix`
    ([C, 6, 6]), by central differences of the real pose transform."""
    columns = []
    for k in range(6):
        latent = torch.zeros(len(viewmats), 6, dtype=F64)
        latent[:, k] = 1e-5
        step = (matrix @ latent[..., None])[..., 0]
        plus, _ = project_points(corrected_viewmats(parameterization, viewmats, step, centers), Ks, points)
        minus, _ = project_points(corrected_viewmats(parameterization, viewmats, -step, centers), Ks, points)
        columns.append(((plus - minus) / (2e-5 * size)).reshape(len(viewmats), -1))
    jacobian = torch.stack(columns, -1)
    return jacobian.transpose(1, 2) @ jacobian / jacobian.shape[1]


@pytest.mark.parametrize("parameterization", ["camera", "object"])
def test_preconditioner_whitens_the_image_motion(parameterization):
    viewmats, Ks = orbit_cameras()
    points = 0.5 * torch.randn(400, 3, generator=torch.Generator().manual_seed(2), dtype=F64)
    centers = torch.tensor([[0.1, -0.2, 0.05]], dtype=F64).expand(3, 3).contiguous()
    matrix = preconditioner(parameterization, viewmats, Ks, 64, 64, points, centers, regularization=1e-6)
    # The Jacobian of the projected points with respect to the latent parameters, J P, has J^T J / n close to I.
    moments = _latent_moments(parameterization, viewmats, Ks, points, centers, matrix)
    torch.testing.assert_close(moments, torch.eye(6, dtype=F64).expand(3, 6, 6), rtol=0, atol=1e-3)


@pytest.mark.parametrize("parameterization", ["camera", "object"])
def test_preconditioner_damping_and_points_behind_a_camera(parameterization):
    """The default damping r = 0.1 (`camera.precondition_reg`) went untested (the test above runs at 1e-6: a P that
    ignored r passed): with A = M + r diag(M), the latent moments are A^-1/2 M A^-1/2. Points behind a camera are
    left out of its M: adding some changes no P."""
    viewmats, Ks = orbit_cameras()
    points = 0.5 * torch.randn(400, 3, generator=torch.Generator().manual_seed(2), dtype=F64)
    centers = torch.tensor([[0.1, -0.2, 0.05]], dtype=F64).expand(3, 3).contiguous()
    identity = torch.eye(6, dtype=F64).expand(3, 6, 6)
    plain = _latent_moments(parameterization, viewmats, Ks, points, centers, identity)  # M
    damped = plain + torch.diag_embed(0.1 * torch.diagonal(plain, dim1=1, dim2=2))
    eigenvalues, eigenvectors = torch.linalg.eigh(damped)
    inverse_root = (eigenvectors * eigenvalues.rsqrt()[:, None, :]) @ eigenvectors.transpose(1, 2)
    matrix = preconditioner(parameterization, viewmats, Ks, 64, 64, points, centers, regularization=0.1)
    moments = _latent_moments(parameterization, viewmats, Ks, points, centers, matrix)
    torch.testing.assert_close(moments, inverse_root @ plain @ inverse_root, rtol=0, atol=1e-6)
    assert (torch.linalg.eigvalsh(moments) < 1 - 0.02).any()  # damped: not whitened
    # points behind camera 0 (past its centre, away from the object): camera 0's P is unchanged
    centre = torch.linalg.inv(viewmats[0])[:3, 3]
    behind = centre + (centre - centers[0]) * torch.linspace(0.1, 0.5, 20, dtype=F64)[:, None]
    with_behind = preconditioner(parameterization, viewmats, Ks, 64, 64, torch.cat([points, behind]), centers,
                                 regularization=0.1)
    torch.testing.assert_close(with_behind[0], matrix[0], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("width, height", [(96, 64), (64, 96)])
def test_preconditioner_measures_the_image_motion_in_the_longer_image_side(width, height):
    """Pixels are divided by max(W, H), the image size of the silhouette terms; every other test has a square image,
    where dividing by min(W, H) passed unnoticed. On a landscape and a portrait image the latent moments, measured in
    units of the longer side, are I (by the shorter side they would be (64 / 96)^2 I = 0.44 I)."""
    viewmats, _ = orbit_cameras()
    focal = 32 / math.tan(math.radians(15))
    Ks = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=F64).expand(3, 3, 3)
    points = 0.5 * torch.randn(400, 3, generator=torch.Generator().manual_seed(2), dtype=F64)
    centers = torch.tensor([[0.1, -0.2, 0.05]], dtype=F64).expand(3, 3).contiguous()
    for parameterization in ("camera", "object"):
        matrix = preconditioner(parameterization, viewmats, Ks, width, height, points, centers, regularization=1e-6)
        moments = _latent_moments(parameterization, viewmats, Ks, points, centers, matrix, size=max(width, height))
        torch.testing.assert_close(moments, torch.eye(6, dtype=F64).expand(3, 6, 6), rtol=0, atol=1e-3)


def _configured_cameras(**camera) -> tuple[CameraOptimizer, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The camera optimizer that the trainer builds (`camera_setup.training_cameras`) for the quick preset with the
    `camera` group's fields replaced, on 4 orbit cameras (float64); with its Ks and object points."""
    viewmats, Ks = orbit_cameras(count=4)
    points = 0.5 * torch.randn(200, 3, generator=torch.Generator().manual_seed(3), dtype=F64)
    config = load_preset("quick", camera=camera, lr={"pose": 3e-3, "pose_translation_scale": 0.25})
    center = torch.tensor([0.1, -0.2, 0.05], dtype=F64)
    return training_cameras(config, viewmats, center, Ks, 64, 64, points), viewmats, Ks, points


@pytest.mark.parametrize("parameterization", ["camera", "object"])
def test_the_configs_parameterization_decides_what_a_rotation_parameter_turns_about(parameterization):
    """`--camera-param` (`camera.parameterization`) reaches the optimizer only through
    `CameraOptimizerSettings.from_config`; no test built one from a config asking for "camera", so a bridge that
    always gave "object" passed. A pure rotation parameter of "camera" turns the camera about its own centre (the
    centre stays); one of "object" turns it about the object centre (the centre moves, the object stays in view)."""
    cameras, viewmats, _, _ = _configured_cameras(parameterization=parameterization, precondition=False)
    assert cameras.settings.parameterization == parameterization
    with torch.no_grad():
        cameras.rotations[1] = torch.tensor([0.05, -0.03, 0.02], dtype=F64)
    moved = camera_centers(cameras.viewmats()) - camera_centers(viewmats)
    turn = cameras.viewmats()[1, :3, :3] @ viewmats[1, :3, :3].T
    angle = math.acos(min(1.0, (turn.trace().item() - 1) / 2))
    assert angle == pytest.approx(math.sqrt(0.05 ** 2 + 0.03 ** 2 + 0.02 ** 2), rel=1e-9)  # turned by |w| either way
    if parameterization == "camera":
        torch.testing.assert_close(moved, torch.zeros_like(moved), rtol=0, atol=1e-12)
    else:  # about the object ~4 away: the centre moves by about 4 |w| = 0.25
        assert moved[1].norm() > 0.15 and moved[[0, 2, 3]].abs().max() == 0


def test_the_configs_preconditioning_and_its_damping_reach_the_camera_optimizer():
    """`camera.precondition` and `camera.precondition_reg` reach the optimizer only through
    `CameraOptimizerSettings.from_config` (as do the pose learning rates); a bridge that ignored them passed every
    test. Off, P is the identity; on with r = 0.01, P is CamP's at that damping, measurably not the default 0.1's."""
    plain, _, _, _ = _configured_cameras(precondition=False)
    assert not plain.settings.precondition
    assert torch.equal(plain.preconditioner, torch.eye(6, dtype=F64).expand(4, 6, 6))
    assert [group["lr"] for group in plain.optimizer.param_groups] == [3e-3, 3e-3 * 0.25]
    damped, viewmats, Ks, points = _configured_cameras(precondition=True, precondition_reg=0.01)
    assert damped.settings.precondition_reg == 0.01
    expected = {reg: preconditioner("object", viewmats, Ks, 64, 64, points, damped.object_centers, reg)
                for reg in (0.01, 0.1)}
    torch.testing.assert_close(damped.preconditioner, expected[0.01], rtol=1e-10, atol=0)
    # the two dampings' P differ by 4.6-6.4 % of their largest entry (measured), far beyond the tolerance above
    change = (expected[0.01] - expected[0.1]).abs().amax(dim=(1, 2)) / expected[0.1].abs().amax(dim=(1, 2))
    assert change.min() > 0.03, change


def _optimizer(settings: CameraOptimizerSettings, dtype=torch.float32) -> CameraOptimizer:
    viewmats, Ks = orbit_cameras(count=4, dtype=dtype)
    points = 0.5 * torch.randn(200, 3, generator=torch.Generator().manual_seed(3), dtype=dtype)
    return CameraOptimizer(viewmats, settings, torch.tensor([0.1, -0.2, 0.05], dtype=dtype), Ks, 64, 64, points)


@pytest.mark.parametrize("parameterization", ["camera", "object"])
def test_unrendered_cameras_do_not_move(parameterization):
    """Cameras 0 and 1 alternate, 2 and 3 are never rendered. Camera 1 resting while camera 0 steps is the case
    that matters: it has Adam momentum, which a plain step would carry on through its zero gradient row."""
    cameras = _optimizer(CameraOptimizerSettings(parameterization=parameterization, lr=1e-2))
    for step in range(6):
        views = torch.tensor([step % 2])
        resting = cameras.params().detach()[1].clone()
        cameras(views)[:, :3, 3].sum().backward()
        cameras.step(views)
        cameras.zero_grad()
        if step > 0 and step % 2 == 0:  # camera 1 has stepped before and rests now
            assert torch.equal(cameras.params().detach()[1], resting)
            for param in (cameras.rotations, cameras.translations):  # and keeps its moments (they decayed)
                state = cameras.optimizer.state[param]
                assert all(torch.equal(state[key][1], moments[param, key]) for key in ("exp_avg", "exp_avg_sq"))
        if step % 2 == 1:  # camera 1 stepped: its moments, to be kept through its next rest
            moments = {(param, key): cameras.optimizer.state[param][key][1].clone()
                       for param in (cameras.rotations, cameras.translations) for key in ("exp_avg", "exp_avg_sq")}
    params = cameras.params().detach()
    assert params[:2].abs().max() > 1e-3
    assert torch.all(params[2:] == 0)
    torch.testing.assert_close(cameras.viewmats()[2:], cameras.base_viewmats[2:], rtol=0, atol=1e-6)


def test_a_first_step_leaves_the_resting_cameras_moments_at_zero():
    """After a reset (a round's rebase, the average) Adam has no state yet; a term that reaches cameras not rendered
    this step (the epipolar one) must not leave them momentum from a step they did not take."""
    cameras = _optimizer(CameraOptimizerSettings(lr=1e-2))
    cameras(torch.arange(4))[:, :3, 3].sum().backward()  # every camera has a gradient
    cameras.step(torch.tensor([0]))
    for param in (cameras.rotations, cameras.translations):
        state = cameras.optimizer.state[param]
        assert state["exp_avg"][0].abs().max() > 0 and torch.all(state["exp_avg"][1:] == 0)
        assert torch.all(state["exp_avg_sq"][1:] == 0) and torch.all(param.detach()[1:] == 0)
    fresh = _optimizer(CameraOptimizerSettings(lr=1e-2))
    fresh.step(torch.tensor([0]))  # no gradient at all: Adam makes no state, and none is restored (was a KeyError)
    assert torch.all(fresh.params() == 0)


def test_each_lbfgs_iteration_of_refine_counts():
    """`refine(loss, n)` with n = 1, 2, 3 ends ever closer: torch's default budget of 5n/4 evaluations let two
    iterations stop where one did (`warpbags eval --refine-iters 2` changed nothing). Already the first iteration
    ends below the start (measured 0.86 of it): without the strong-Wolfe line search, L-BFGS's first step of
    lr / |gradient|_1 overshoots to 37x the start, and the later iterations still ended ever closer."""
    losses = []
    for iterations in (1, 2, 3):
        cameras = _optimizer(CameraOptimizerSettings())
        target = cameras.viewmats().clone()
        target[:, :3, 3] += torch.tensor([0.3, -0.2, 0.1])

        def loss_of(viewmats):
            return ((viewmats - target) ** 2).sum()

        start = float(loss_of(cameras.viewmats()))
        cameras.refine(loss_of, iterations)
        losses.append(float(loss_of(cameras.viewmats())))
    assert 0.9 * start > losses[0] > losses[1] > losses[2], (start, losses)


def test_the_camera_optimizer_is_an_ordinary_torch_module():
    # Its poses come from forward; Module.apply(fn) keeps torch's meaning, so a parent module can initialize or
    # move it like any other submodule.
    cameras = _optimizer(CameraOptimizerSettings())
    visited = []
    assert cameras.apply(visited.append) is cameras and visited == [cameras]
    torch.testing.assert_close(cameras(torch.tensor([2, 0])), cameras.viewmats()[[2, 0]], rtol=0, atol=0)
    assert cameras.double().base_viewmats.dtype == torch.float64


def test_fixed_gauge_camera_keeps_its_pose_and_state_round_trips():
    settings = CameraOptimizerSettings(fix_first_camera=True, lr=1e-2)
    cameras = _optimizer(settings)
    for _ in range(3):
        cameras()[:, :3, 3].pow(2).sum().backward()
        cameras.step()
        cameras.zero_grad()
    torch.testing.assert_close(cameras.viewmats()[0], cameras.base_viewmats[0], rtol=0, atol=0)
    assert (cameras.viewmats()[1:] - cameras.base_viewmats[1:]).abs().max() > 1e-4
    assert cameras.movable_cameras() == list(range(1, cameras.num_cameras))
    assert _optimizer(CameraOptimizerSettings(lr=1e-2)).movable_cameras() == list(range(cameras.num_cameras))
    restored = _optimizer(settings)
    checkpoint = io.BytesIO()  # as a checkpoint goes: saved, then loaded (state() holds the live tensors)
    torch.save(cameras.state(), checkpoint)
    checkpoint.seek(0)
    restored.load_state(torch.load(checkpoint, weights_only=False))
    torch.testing.assert_close(restored.viewmats(), cameras.viewmats(), rtol=0, atol=0)
    # Adam's moments came along too: one more identical step lands both at the same parameters
    for optimizer in (cameras, restored):
        optimizer()[:, :3, 3].pow(2).sum().backward()
        optimizer.step()
        optimizer.zero_grad()
    torch.testing.assert_close(restored.params(), cameras.params(), rtol=0, atol=0)


def test_a_checkpoint_from_before_the_base_poses_were_named_so_loads():
    cameras = _optimizer(CameraOptimizerSettings(lr=1e-2))
    cameras()[:, :3, 3].pow(2).sum().backward()
    cameras.step()
    cameras.rebase()  # the base poses are no longer the starting ones
    state = cameras.state()
    state["module"] = {("viewmats_init" if name == "base_viewmats" else name): value
                       for name, value in state["module"].items()}
    restored = _optimizer(CameraOptimizerSettings(lr=1e-2))
    restored.load_state(state)
    torch.testing.assert_close(restored.base_viewmats, cameras.base_viewmats, rtol=0, atol=0)


def test_pose_kernels_compile_for_sm90(tmp_path):
    import warpbags.kernels.pose as pose_kernels

    for dtype in (torch.float32, F64):  # instantiate both kernels' overloads in both precisions
        viewmats, _ = orbit_cameras(count=2, dtype=dtype)
        params = torch.zeros(2, 6, dtype=dtype, requires_grad=True)
        centers = torch.zeros(2, 3, dtype=dtype)
        (corrected_viewmats("object", viewmats, params, centers).sum()
         + corrected_viewmats("camera", viewmats, params).sum()).backward()
    try:
        artifacts = wp.compile_aot_module(pose_kernels, arch=90, module_dir=tmp_path)
    except Exception as error:
        if "nvrtc" in str(error).lower():
            pytest.skip(f"NVRTC is not available in this Warp build: {error}")
        raise
    sources = "".join(path.read_text() for path in tmp_path.rglob("*.cu"))
    assert artifacts and "apply_object_deltas_kernel" in sources


def test_a_frozen_orbit_stays_put_and_its_release_does_not_jump():
    cameras = _optimizer(CameraOptimizerSettings(lr=1e-2))
    cameras.set_orbit_free(False)
    for _ in range(5):
        cameras()[:, :3, :].pow(2).sum().backward()  # a loss every parameter's gradient reaches
        cameras.step()
        cameras.zero_grad()
    params = cameras.params().detach()
    assert torch.all(params[:, :2] == 0) and params[:, 2:].abs().max() > 1e-3
    latent = torch.cat([cameras.rotations, cameras.translations], dim=1).detach()
    hidden = (cameras.preconditioner @ latent[..., None])[..., :2, 0]
    assert hidden.abs().max() > 1e-3  # Adam moved the latents along the rows that were held
    before = cameras.viewmats()
    cameras.set_orbit_free(True)
    torch.testing.assert_close(cameras.viewmats(), before, rtol=0, atol=1e-6)  # the release rebased: no jump
    assert torch.all(cameras.rotations == 0) and not cameras.optimizer.state
    cameras()[:, :3, :].pow(2).sum().backward()
    cameras.step()
    assert cameras.params().detach()[:, :2].abs().max() > 1e-4  # the orbit moves now


def test_an_unknown_parameterization_is_refused():
    """The config refuses it (`TrainConfig.validate`); a CameraOptimizer given one anyway refuses it where its poses
    are first computed (`corrected_viewmats`): in its preconditioner, or without one in its first forward."""
    with pytest.raises(WarpbagsError, match="camera.parameterization must be object or camera, got 'twist'"):
        load_preset("quick", camera={"parameterization": "twist"})
    for precondition in (True, False):
        with pytest.raises(WarpbagsError, match="must be one of camera, object, got 'twist'"):
            _optimizer(CameraOptimizerSettings(parameterization="twist", precondition=precondition)).viewmats()


def test_orbit_freezing_needs_the_object_parameterization():
    with pytest.raises(WarpbagsError, match="object parameterization"):
        _optimizer(CameraOptimizerSettings(parameterization="camera", precondition=False)).set_orbit_free(False)


@pytest.mark.parametrize("parameterization", ["camera", "object"])
def test_a_turn_about_the_object_keeps_its_centre_and_turns_by_the_angle(parameterization):
    cameras = _optimizer(CameraOptimizerSettings(parameterization=parameterization, precondition=False, lr=1e-2),
                         dtype=F64)
    cameras()[:, :3, 3].sum().backward()  # corrections and Adam moments, which the turn folds in and clears
    cameras.step()
    before = cameras.viewmats()
    turns = hypothesis_turns("zx", (30.0, 15.0))
    assert [label for label, _ in turns] == ["+15 deg about z", "-15 deg about z", "+15 deg about x",
                                             "-15 deg about x", "+30 deg about z", "-30 deg about z",
                                             "+30 deg about x", "-30 deg about x"]
    assert [label for label, _ in hypothesis_turns("y", (180.0,))] == ["+180 deg about y"]  # -180 is the same turn
    cameras.turn_about_object(1, turns[0][1].to(before))
    after = cameras.viewmats()
    torch.testing.assert_close(after[[0, 2]], before[[0, 2]], rtol=0, atol=1e-12)  # the others stay
    center = cameras.object_centers[1]
    seen = [(pose[:3, :3] @ center + pose[:3, 3]) for pose in (before[1], after[1])]
    torch.testing.assert_close(seen[1], seen[0], rtol=0, atol=1e-12)  # the object centre stays where it was seen
    turn = after[1, :3, :3] @ before[1, :3, :3].T  # in the camera's frame: about its z axis by +15 deg, not -15
    cos, sin = math.cos(math.radians(15)), math.sin(math.radians(15))
    expected = torch.tensor([[cos, -sin, 0], [sin, cos, 0], [0, 0, 1]], dtype=F64)
    torch.testing.assert_close(turn, expected, rtol=0, atol=1e-12)
    assert torch.all(cameras.rotations == 0) and not cameras.optimizer.state


def test_the_anchor_is_averaged_over_the_steps_rendered_cameras():
    """`anchor_loss(views)`, which `camera.round_anchor` weighs: 1/2 |delta|^2 of a camera rendered alone, a quarter
    of that when it is one of four rendered views (the mean over the step's cameras, the scale at which the config's
    measurements were taken; a sum would charge it 4x as much)."""
    cameras = _optimizer(CameraOptimizerSettings(precondition=False), dtype=F64)  # real parameters = latents
    with torch.no_grad():
        cameras.rotations[1] = torch.tensor([0.1, 0.0, 0.0], dtype=F64)
        cameras.translations[1] = torch.tensor([0.0, 0.2, 0.0], dtype=F64)
    alone = 0.5 * (0.1 ** 2 + 0.2 ** 2)
    assert cameras.anchor_loss(torch.tensor([1])).item() == pytest.approx(alone, rel=1e-12)
    assert cameras.anchor_loss(torch.arange(4)).item() == pytest.approx(alone / 4, rel=1e-12)


def test_the_average_of_the_estimates_becomes_the_poses_and_survives_a_checkpoint():
    cameras = _optimizer(CameraOptimizerSettings(lr=1e-2), dtype=torch.float64)
    cameras.apply_average()  # none accumulated: nothing changes
    torch.testing.assert_close(cameras.viewmats(), cameras.base_viewmats, rtol=0, atol=0)
    estimates = []
    for _ in range(3):
        cameras()[:, :3, 3].pow(2).sum().backward()
        cameras.step()
        cameras.zero_grad()
        cameras.accumulate_average()
        estimates.append(cameras.viewmats())
    saved = io.BytesIO()
    torch.save(cameras.state(), saved)
    saved.seek(0)
    restored = _optimizer(CameraOptimizerSettings(lr=1e-2), dtype=torch.float64)
    restored.load_state(torch.load(saved, weights_only=False))
    expected = mean_viewmats(sum(e[:, :3, :3] for e in estimates), sum(camera_centers(e) for e in estimates), 3)
    for optimizer in (cameras, restored):
        optimizer.apply_average()
        torch.testing.assert_close(optimizer.viewmats(), expected, rtol=0, atol=1e-12)
        assert torch.all(optimizer.params() == 0) and optimizer.average_count == 0
    assert (expected - estimates[-1]).abs().max() > 1e-6  # the mean is not the last estimate
    # a checkpoint of a warpbags without the average loads with an empty one
    old = cameras.state()
    old = {"module": {k: v for k, v in old["module"].items() if not k.startswith("average_")},
           "optimizer": old["optimizer"]}
    restored.load_state(old)
    assert restored.average_count == 0


def test_a_gauge_camera_keeps_its_given_pose_through_the_average():
    cameras = _optimizer(CameraOptimizerSettings(fix_first_camera=True, lr=1e-2))
    start = cameras.viewmats().double()
    given = cameras.viewmats()[0].clone()
    estimates = []
    for _ in range(3):
        cameras()[:, :3, 3].pow(2).sum().backward()
        cameras.step()
        cameras.zero_grad()
        cameras.accumulate_average()
        estimates.append(cameras.viewmats().double())
    cameras.apply_average()
    assert torch.equal(cameras.viewmats()[0], given)  # not re-projected onto SO(3) in float32
    # the others at their mean, which is not where they started
    mean = mean_viewmats(sum(e[:, :3, :3] for e in estimates), sum(camera_centers(e) for e in estimates), 3)
    torch.testing.assert_close(cameras.viewmats()[1:].double(), mean[1:], rtol=0, atol=1e-6)
    assert (mean[1:] - start[1:]).abs().max() > 1e-4
