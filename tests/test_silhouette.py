"""Mask-based pose signals: the centroid start recovers pan/tilt errors, silhouette coherence charges poses whose
silhouettes disagree and its solve brings noisy cameras in, and the silhouette losses pull a camera whose render
misses the mask entirely (where a per-pixel mask loss has no gradient)."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import look_at

import warpbags
from warpbags.alignment import pose_errors
from warpbags.configs.train import load_preset
from warpbags.camera_optimizer import CameraOptimizer, CameraOptimizerSettings, corrected_viewmats
from warpbags.camera_setup import coherent_start, starting_poses
from warpbags.cameras import camera_centers, pixel_directions, project_points
from warpbags.data import SyntheticOptions, ensure_synthetic_scene, load_scene
from warpbags.data.noise import perturb_viewmats
from warpbags.kernels.coherence import BEHIND_CAMERA_DISTANCE
from warpbags.lie import so3_exp
from warpbags.losses import mask_loss
from warpbags.silhouette import (COHERENCE_SAMPLES, EDGE_POINTS, SilhouetteTargets, centroid_start, mask_centroids,
                                 nearest_distances, rays_meeting_point)
from warpbags.wrapper import least_outside_samples, nearest_points


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    options = SyntheticOptions(views=16, width=96, height=96)
    return load_scene(ensure_synthetic_scene(options, cache_dir=tmp_path_factory.mktemp("cache")), name="tiny")


def test_rays_meeting_point_is_exact_for_rays_through_one_point():
    point = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)
    origins = torch.randn(5, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 4
    directions = (point - origins) / (point - origins).norm(dim=-1, keepdim=True)
    torch.testing.assert_close(rays_meeting_point(origins, directions), point, rtol=0, atol=1e-10)


def test_rays_meeting_point_with_min_spread_refuses_nearly_parallel_rays():
    """A forward-facing capture: parallel optical axes meet nowhere (`data.loaders.object_center` falls back)."""
    origins = torch.tensor([[-1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    parallel = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand(3, 3)
    assert rays_meeting_point(origins, parallel, min_spread=1e-3) is None
    converging = torch.tensor([[1.0, 0.0, 4.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 4.0]], dtype=torch.float64)
    converging = converging / converging.norm(dim=-1, keepdim=True)  # through (0, 0, 4)
    point = rays_meeting_point(origins, converging, min_spread=1e-3)
    torch.testing.assert_close(point, torch.tensor([0.0, 0.0, 4.0], dtype=torch.float64), rtol=0, atol=1e-12)


def test_centroid_start_recovers_an_off_axis_camera(scene):
    views = scene.subset(scene.train_views(6))
    truth = views.viewmats.double()
    # Camera 2 is panned and tilted by 12 degrees about its own centre (the object leaves the image centre); the
    # others are exact, so the centroid rays still meet at the object and the bad camera is turned back onto it.
    turn = torch.eye(4, dtype=torch.float64).repeat(6, 1, 1)
    turn[2, :3, :3] = so3_exp(torch.deg2rad(torch.tensor([8.0, -9.0, 0.0], dtype=torch.float64)))
    noisy = turn @ truth
    before = pose_errors(noisy, truth, alignment="none")["rotation_errors_deg"]
    start, center = centroid_start(views.masks, noisy, views.Ks)
    after = pose_errors(start, truth, alignment="none")["rotation_errors_deg"]
    assert before[2] > 11.9
    # The ray through a silhouette's centroid passes near, not through, the object's 3D centre (measured 1.4-3.9 deg
    # on the exact cameras at 96 px), so this is a start for the optimization, not an answer: 12.0 -> 3.3 deg.
    assert after[2] < 0.35 * before[2], after
    assert after.max() < 4.5
    assert center.norm() < 0.3  # the synthetic object sits at the origin of the normalized world


@pytest.mark.parametrize("centroid_start", [True, False])
def test_the_mask_centroid_start_turns_the_cameras_only_when_asked(scene, centroid_start):
    """`--set camera.centroid_start=false` was never tested (dropping the setting passed): off, the given poses come
    back unchanged; on, the noisy cameras are turned."""
    views = scene.subset(scene.train_views(4))
    noisy = perturb_viewmats(views.viewmats, 10.0, 0.0, seed=3)
    config = load_preset("quick", camera={"centroid_start": centroid_start})
    start, _ = starting_poses(noisy, views.masks, views.Ks, config, lambda message: None)
    assert torch.equal(start, noisy) is not centroid_start


@pytest.mark.parametrize("pose_opt", [True, False])
def test_a_forward_facing_rig_keeps_its_poses_and_takes_the_origin_as_object_centre(pose_opt):
    """Parallel optical axes (four cameras on a line, a forward-facing capture) have no meeting point: the poses stay
    as given, the centre is the origin and the log says why (a singular solve raised numpy's LinAlgError, even for
    the baseline, which never uses the centre)."""
    viewmats = torch.eye(4).repeat(4, 1, 1)
    viewmats[:, 0, 3] = -torch.arange(4.0)  # camera centres at x = 0..3, all looking down +z
    Ks = torch.tensor([[50.0, 0, 16], [0, 50, 16], [0, 0, 1]]).repeat(4, 1, 1)
    masks = torch.zeros(4, 32, 32)
    masks[:, 12:20, 12:20] = 1
    messages = []
    start, center = starting_poses(viewmats, masks, Ks, load_preset("quick", pose_opt=pose_opt), messages.append)
    assert torch.equal(start, viewmats) and torch.equal(center, torch.zeros(3))
    assert any("nearly parallel" in message for message in messages), messages


def test_without_masks_the_object_centre_is_where_the_optical_axes_meet():
    """Four cameras around a point off the origin, no masks: the poses stay as given and the centre is that point.
    The test above has identity rotations only, where taking a column of the world-to-camera rotation for the
    optical axis instead of its third row passed; here the two differ."""
    target = torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64)
    viewmats = torch.stack([look_at(torch.tensor([4 * math.cos(a), 4 * math.sin(a), 0.7], dtype=torch.float64), target)
                            for a in (0.0, 1.6, 3.1, 4.7)]).float()
    Ks = torch.tensor([[100.0, 0, 32], [0, 100, 32], [0, 0, 1]]).repeat(4, 1, 1)
    messages = []
    start, center = starting_poses(viewmats, None, Ks, load_preset("quick"), messages.append)
    assert torch.equal(start, viewmats) and messages == ["no masks: no mask-centroid start"], messages
    torch.testing.assert_close(center.double(), target, rtol=0, atol=1e-5)


def test_mask_centroids_and_edge_pixels_lie_at_pixel_centres():
    """Pixel (i, j) covers [j, j + 1) x [i, i + 1) in the pixel coordinates that `project_points` and the Ks use, so
    its centre is (j + 0.5, i + 0.5); dropping the half pixel moved every centroid ray and chamfer edge by half a
    pixel up and left, and no test saw it. A non-square image, so that x and y cannot be swapped unnoticed."""
    masks = torch.zeros(2, 6, 9, dtype=torch.float64)
    masks[0, 1, 7] = 1.0
    masks[1, 4, 2] = 1.0
    torch.testing.assert_close(mask_centroids(masks), torch.tensor([[7.5, 1.5], [2.5, 4.5]], dtype=torch.float64),
                               rtol=0, atol=1e-12)
    # a 3 x 4 block at rows 2-4, columns 3-6 of a 10 x 12 mask: its centroid is the block's centre, its edge pixels
    # (the chamfer's) are the centres of the block's 10 border pixels, and its coherence rays go through the centres
    # of its 12 pixels
    block = torch.zeros(1, 10, 12)
    block[0, 2:5, 3:7] = 1.0
    torch.testing.assert_close(mask_centroids(block), torch.tensor([[5.0, 3.5]]), rtol=0, atol=1e-6)
    targets = SilhouetteTargets(block)
    border = {(x + 0.5, y + 0.5) for y in range(2, 5) for x in range(3, 7) if y in (2, 4) or x in (3, 6)}
    assert len(border) == 10 and {tuple(edge) for edge in targets.edges[0].tolist()} == border
    inside = {(x + 0.5, y + 0.5) for y in range(2, 5) for x in range(3, 7)}
    assert {tuple(pixel) for pixel in targets.foreground[0].tolist()} == inside


def _coherence_case(scene, count=4):
    views = scene.subset(scene.train_views(count))
    truth, Ks = views.viewmats.double(), views.Ks.double()
    targets = SilhouetteTargets(views.masks)
    center = torch.zeros(3, dtype=torch.float64)  # the synthetic object sits at the origin
    return views, truth, Ks, targets, center, targets.object_radius(truth, Ks, center)


def _turned(viewmats, camera, rotation_deg):
    """Camera `camera` turned about the object centre (the origin) by [3] degrees in its own frame (z: roll)."""
    turn = torch.zeros(len(viewmats), 6, dtype=torch.float64)
    turn[camera, :3] = torch.deg2rad(torch.tensor(rotation_deg, dtype=torch.float64))
    return corrected_viewmats("object", viewmats, turn, torch.zeros(len(viewmats), 3, dtype=torch.float64))


def test_coherence_is_zero_at_the_true_poses_and_charges_a_rolled_camera(scene):
    views, truth, Ks, targets, center, radius = _coherence_case(scene)
    at_truth = targets.coherence_loss(truth, Ks, center, radius).item()
    rolled = targets.coherence_loss(_turned(truth, 2, [0.0, 0.0, 10.0]), Ks, center, radius).item()
    # Measured 3.0e-5 (masks rasterized at 96 px) against 7.8e-4 with one camera rolled by 10 deg.
    assert at_truth < 6e-5
    assert rolled > 10 * at_truth


def _cut_by_the_frame(views, Ks, cut=30):
    """The views' masks cropped by `cut` px on the left and top, and their intrinsics moved with them."""
    cut_Ks = Ks.clone()
    cut_Ks[:, 0, 2] -= cut
    cut_Ks[:, 1, 2] -= cut
    return views.masks[:, cut:, cut:], cut_Ks


def test_masks_continued_beyond_the_frame_keep_a_cut_capture_coherent_at_its_true_poses(scene):
    """The frame cuts the object (the views cropped by 30 px on the left and top, the principal point moved with
    them): counted as background, the border makes the true poses incoherent; continued beyond it, they stay so."""
    views, truth, Ks, whole, center, radius = _coherence_case(scene, count=6)
    masks, cut_Ks = _cut_by_the_frame(views, Ks)
    assert (masks[:, :, 0].amax(1) > 0.5).sum() >= 3  # the object meets the cut border in most views
    uncut = whole.coherence_loss(truth, Ks, center, radius).item()
    background = SilhouetteTargets(masks).coherence_loss(truth, cut_Ks, center, radius).item()
    continued = SilhouetteTargets(masks, continued_beyond_frame=True).coherence_loss(truth, cut_Ks, center, radius).item()
    # Measured 2.1e-2 image sizes as background, 2.3e-4 continued, 1.3e-4 for the uncut views.
    assert background > 20 * max(continued, uncut), (background, continued, uncut)
    assert continued < 3 * uncut + 1e-5, (continued, uncut)


def test_coherence_pulls_a_camera_whose_rays_miss_the_other_silhouettes(scene):
    views, truth, Ks, targets, center, radius = _coherence_case(scene)
    # Camera 1 moved 1.5 units sideways (its x axis), not turned: no ray through its mask meets the object's region
    # inside the other views' cones, so a per-pixel loss has nothing to say; the distances outside the masks do.
    moved = truth.clone()
    moved[1, 0, 3] -= 1.5
    moved.requires_grad_(True)
    loss = targets.coherence_loss(moved, Ks, center, radius)
    loss.backward()
    assert loss.item() > 0.05  # every ray misses by a good part of the image (measured 0.12)
    assert moved.grad[1, 0, 3] < 0  # and descent pulls it back the way it came (t_x up again)
    with torch.no_grad():
        step = moved - 0.5 * moved.grad / moved.grad[1].norm()
        assert targets.coherence_loss(step, Ks, center, radius) < loss


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_coherence_charges_points_behind_another_camera_as_outside_its_silhouette(dtype):
    """Camera 1 stands 10 units down camera 0's axis, facing the same way: the object region camera 0 looks at
    (5 units ahead) lies behind camera 1. Projected with a stand-in depth of 1 those points landed on camera 1's
    mask and camera 0's rays were charged nearly nothing, though no point behind a camera is in its silhouette cone
    (a camera turned away from the object, as a start without the mask-centroid turn can leave it)."""
    viewmats = torch.eye(4, dtype=dtype).repeat(2, 1, 1)
    viewmats[1, 2, 3] = -10.0  # centre at z = 10, looking down +z like camera 0
    Ks = torch.tensor([[50.0, 0, 16], [0, 50, 16], [0, 0, 1]], dtype=dtype).repeat(2, 1, 1)
    masks = torch.zeros(2, 32, 32)
    masks[:, 12:20, 12:20] = 1
    targets = SilhouetteTargets(masks)
    center = torch.tensor([0.0, 0.0, 5.0], dtype=dtype)
    # every sample of camera 0's rays is behind camera 1, every one of camera 1's in front of camera 0 and on its mask
    loss = targets.coherence_loss(viewmats, Ks, center, 1.0).item()
    assert loss == pytest.approx(BEHIND_CAMERA_DISTANCE / 2, rel=1e-6)
    behind = torch.tensor([[0.0, 0.0, 5.0]], dtype=dtype)
    assert targets._outside_other_views(behind, 0, viewmats, Ks).item() == BEHIND_CAMERA_DISTANCE
    # camera 1 moved into the middle of camera 0's depth range: the search (kernels/coherence.py) takes the sample
    # in front of it that passes through its mask, as trying every sample does, not one behind it
    viewmats[1, 2, 3] = -5.0
    centers = camera_centers(viewmats)
    depths = torch.linspace(4.0, 6.0, COHERENCE_SAMPLES, dtype=dtype)[None].repeat(2, 1)
    rays = pixel_directions(targets.foreground[0].to(dtype), Ks[0])
    chosen = least_outside_samples(rays, torch.zeros(len(rays), dtype=torch.long), centers, depths, viewmats, Ks,
                                   targets.outside_distance, targets.margin, targets.size)
    points = rays[:, None] * depths[0][None, :, None]
    totals = targets._outside_other_views(points.reshape(-1, 3), 0, viewmats, Ks).reshape(points.shape[:2])
    assert (totals == BEHIND_CAMERA_DISTANCE).any(dim=1).all() and (totals.min(dim=1).values < 1).all()
    assert torch.equal(chosen, totals.argmin(dim=1))


@pytest.mark.parametrize("continued", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_coherence_search_picks_each_rays_least_sample_as_trying_every_sample_does(scene, continued, dtype):
    """The coherence loss's search (kernels/coherence.py: middle-out, a sample dropped once its partial sum exceeds
    the least so far) picks on every ray the sample whose summed distance outside the other masks is least, the first
    of equal ones: what projecting every sample into every other view and taking the argmin gives."""
    views, truth, Ks, _, center, radius = _coherence_case(scene, count=6)
    targets = SilhouetteTargets(views.masks, continued_beyond_frame=continued)
    viewmats, Ks, center = perturb_viewmats(truth, 10.0, 0.2, seed=3).to(dtype), Ks.to(dtype), center.to(dtype)
    centers = camera_centers(viewmats)
    depths = (center - centers).norm(dim=-1)[:, None] + torch.linspace(-radius, radius, COHERENCE_SAMPLES, dtype=dtype)
    picked, least, zero_runs = 0, 0, 0
    for view in range(len(viewmats)):
        rays = pixel_directions(targets.foreground[view].to(dtype), Ks[view]) @ viewmats[view, :3, :3]
        chosen = least_outside_samples(rays, torch.full((len(rays),), view), centers, depths, viewmats, Ks,
                                       targets.outside_distance, targets.margin, targets.size)
        points = centers[view] + rays[:, None] * depths[view][None, :, None]
        totals = targets._outside_other_views(points.reshape(-1, 3), view, viewmats, Ks).reshape(points.shape[:2])
        tolerance = 1e-5 if dtype == torch.float32 else 1e-12
        assert torch.allclose(totals.gather(1, chosen[:, None])[:, 0], totals.min(dim=1).values, rtol=0, atol=tolerance)
        picked += int((chosen == totals.argmin(dim=1)).sum())
        least += len(chosen)
        zero_runs += int(((totals == 0).sum(dim=1) > 1).sum())
    assert zero_runs > 0  # rays through every cone at several samples: the first of the equal ones is taken
    assert picked >= 0.99 * least, (picked, least)


def test_coherent_start_brings_noisy_cameras_in_before_any_gaussian_is_fitted(scene):
    views, truth, Ks, targets, center, radius = _coherence_case(scene, count=6)
    noisy = perturb_viewmats(truth, 15.0, 0.3, seed=1)
    start, center = centroid_start(views.masks, noisy, views.Ks)
    cameras = CameraOptimizer(start.float(), CameraOptimizerSettings(precondition=False), center.float())
    before, after = coherent_start(cameras, targets, views.Ks, center.float(), iterations=100)
    error = lambda viewmats: pose_errors(viewmats.double(), truth, alignment="procrustes")["rotation_error_deg_mean"]  # noqa: E731
    assert after < 0.1 * before
    # Every camera perturbed (15 deg / 0.3, free gauge): measured 6.87 deg after the centroid start and 2.79 after
    # the coherence solve; the photometric terms take it from there.
    assert error(start) > 6.0
    assert error(cameras.viewmats()) < 0.6 * error(start)
    assert torch.equal(cameras.rotations, torch.zeros_like(cameras.rotations))  # solved into the starting poses


def test_coherent_start_solves_from_the_corrected_poses_and_applies_the_corrections_once(scene):
    """Cameras that already hold corrections: the solve starts from their corrected poses and its result replaces
    them (without iterations, the corrected poses themselves), not those corrections composed onto it again."""
    views, truth, Ks, targets, center, radius = _coherence_case(scene, count=6)
    cameras = CameraOptimizer(truth.float(), CameraOptimizerSettings(precondition=False), center.float())
    with torch.no_grad():
        cameras.rotations[1] = torch.tensor([0.02, -0.01, 0.03])
    corrected = cameras.viewmats().detach().clone()
    coherent_start(cameras, targets, views.Ks, center.float(), iterations=0)
    torch.testing.assert_close(cameras.viewmats().detach(), corrected, rtol=0, atol=1e-6)
    assert torch.equal(cameras.rotations, torch.zeros_like(cameras.rotations))


def test_coherent_start_of_a_capture_cut_by_the_frame_needs_the_masks_continued(scene):
    """Six views cropped so that the frame cuts the object: the solve that counts the frame as background moves the
    cameras until the object fits inside every frame, away from the truth; with the masks continued it brings them
    in (the trainer continues them from `camera.coherence_continued_from_views` = 6 views on)."""
    views, truth, Ks, _, _, _ = _coherence_case(scene, count=6)
    masks, cut_Ks = _cut_by_the_frame(views, Ks)
    start, center = centroid_start(masks, perturb_viewmats(truth, 15.0, 0.3, seed=1), cut_Ks)
    error = lambda viewmats: pose_errors(viewmats.double(), truth, alignment="procrustes")["rotation_error_deg_mean"]  # noqa: E731
    solved = {}
    for continued in (False, True):
        cameras = CameraOptimizer(start.float(), CameraOptimizerSettings(precondition=False), center.float())
        coherent_start(cameras, SilhouetteTargets(masks, continued_beyond_frame=continued), cut_Ks.float(),
                       center.float(), iterations=30)
        solved[continued] = error(cameras.viewmats())
    # Measured 7.21 deg after the centroid start; 11.9 after the solve with the frame as background, 5.51 with the
    # masks continued.
    assert solved[True] < 0.85 * error(start)
    assert solved[False] > 1.5 * solved[True], solved


def _two_blobs(offset_px: float):
    """A camera looking at a blob of Gaussians and a mask of that blob shifted sideways by `offset_px`."""
    generator = torch.Generator().manual_seed(0)
    n, size = 200, 64
    means = 0.08 * torch.randn(n, 3, generator=generator)
    viewmat = torch.eye(4)[None].clone()
    viewmat[0, 2, 3] = 4.0
    focal = size / (2 * math.tan(math.radians(15)))
    Ks = torch.tensor([[[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1]]])
    ys, xs = torch.meshgrid(torch.arange(size) + 0.5, torch.arange(size) + 0.5, indexing="ij")
    radius = 0.2 * focal / 4.0
    masks = (((xs - size / 2 - offset_px) ** 2 + (ys - size / 2) ** 2) < radius**2).float()[None]
    return means, viewmat, Ks, masks, size


class _MissedMask:
    """One camera, a blob of Gaussians at the image centre and a mask 22 px to its right: no overlap at all."""

    def __init__(self):
        self.means, viewmat, self.Ks, self.masks, self.size = _two_blobs(offset_px=22.0)
        self.cameras = CameraOptimizer(viewmat, CameraOptimizerSettings(lr=2e-2), torch.zeros(3), self.Ks, self.size,
                                       self.size, self.means)
        self.targets = SilhouetteTargets(self.masks)
        self.views = torch.tensor([0])
        self.opacities = torch.full((len(self.means),), 0.9)

    def alphas(self, viewmats):
        n = len(self.means)
        _, alphas, _ = warpbags.rasterization(self.means, torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4).contiguous(),
                                              torch.full((n, 3), 0.03), self.opacities, torch.full((n, 3), 0.5),
                                              viewmats, self.Ks, self.size, self.size)
        return alphas[..., 0]

    def overlap(self, viewmats) -> float:
        return ((self.alphas(viewmats) * self.masks).sum() / self.masks.sum()).item()

    def blob_image_x(self, viewmats) -> float:
        pixels, _ = project_points(viewmats, self.Ks, torch.zeros(1, 3))
        return pixels[0, 0, 0].item()


@pytest.mark.parametrize("term", ["mask_bce", "distance"])
def test_distance_term_turns_the_camera_towards_a_missed_mask(term):
    case = _MissedMask()
    assert case.overlap(case.cameras.viewmats()) < 1e-4
    alphas = case.alphas(case.cameras())
    loss = mask_loss(alphas, case.masks) if term == "mask_bce" else case.targets.distance_loss(alphas, case.views)
    loss.backward()
    # First-order image motion of the blob under a small gradient-descent step of the real camera parameters.
    with torch.no_grad():
        latent = torch.cat([case.cameras.rotations.grad, case.cameras.translations.grad], 1)
        step = -(case.cameras.preconditioner @ latent[..., None])[..., 0]
        step = 1e-3 * step / step.norm().clamp_min(1e-30)
        moved = corrected_viewmats("object", case.cameras.base_viewmats, step, case.cameras.object_centers)
    shift = case.blob_image_x(moved) - case.blob_image_x(case.cameras.base_viewmats)
    if term == "mask_bce":
        assert shift < 0  # no pull towards the mask (measured -9e-5 px): it only shrinks the render
    else:
        # Towards the mask, 22 px to the right (measured +4.2e-4 px; most of the step shrinks the render instead).
        assert shift > 2e-4


def test_chamfer_term_brings_a_missed_mask_into_view():
    case = _MissedMask()
    loss = lambda viewmats: case.targets.chamfer_loss(case.means, case.opacities, viewmats, case.Ks, case.views)  # noqa: E731
    start = loss(case.cameras.viewmats()).item()
    for _ in range(60):
        value = loss(case.cameras())
        case.cameras.zero_grad()
        value.backward()
        case.cameras.step()
    assert loss(case.cameras.viewmats()).item() < 0.2 * start
    assert case.overlap(case.cameras.viewmats()) > 0.5  # the render now covers most of the mask


def test_distance_outside_a_mask_beyond_the_frame_adds_the_way_back_to_the_border():
    # A mask whose left edge is 20 px from the image's left border: a point 8 px beyond that border is 28 px from
    # it (the border pixel's distance, 20 px, plus 8 to the border), and the distance runs on continuously from
    # inside the image. Zero padding charged it 18 px (half the border pixel's distance, plus 8).
    mask = torch.zeros(1, 40, 64)
    mask[:, 10:30, 20:44] = 1
    targets = SilhouetteTargets(mask)
    border_distance = float(targets.outside_distance[0, 20, 0]) * targets.size
    pixels = torch.tensor([[[-8.0, 20.5], [0.0, 20.5], [0.5, 20.5], [2.5, 20.5]]])
    distances = targets._outside_mask(pixels, torch.tensor([0]))[0] * targets.size
    assert border_distance == pytest.approx(20, abs=0.1)
    assert distances[0].item() == pytest.approx(border_distance + 8, abs=1e-3)
    assert distances[1].item() == pytest.approx(border_distance, abs=1e-3)  # the edge itself: not halved
    assert distances[2].item() == pytest.approx(border_distance, abs=1e-3)  # the border pixel's centre
    assert distances[3].item() == pytest.approx(border_distance - 2, abs=0.1)


def test_nearest_distances_are_the_brute_force_minimum_with_its_gradient():
    generator = torch.Generator().manual_seed(0)
    queries = (100 * torch.rand(40, 2, generator=generator, dtype=torch.float64)).requires_grad_()
    points = (100 * torch.rand(5000, 2, generator=generator, dtype=torch.float64)).requires_grad_()
    weights = torch.rand(40, generator=generator, dtype=torch.float64)
    found = nearest_distances(queries, points)
    brute = torch.cdist(queries, points, compute_mode="donot_use_mm_for_euclid_dist").min(dim=1).values
    torch.testing.assert_close(found, brute, rtol=0, atol=1e-12)
    gradients = torch.autograd.grad((found * weights).sum(), (queries, points))
    expected = torch.autograd.grad((brute * weights).sum(), (queries, points))
    for got, want in zip(gradients, expected):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_nearest_points_are_exact_with_ties_to_the_lowest_index(dtype):
    generator = torch.Generator().manual_seed(1)
    # integer coordinates: many points at equal distances from a query, and duplicates (a clone and its original)
    points = torch.randint(0, 30, (3000, 2), generator=generator).to(dtype)
    queries = torch.randint(-5, 35, (500, 2), generator=generator).to(dtype) + 0.5 * (torch.arange(500) % 2)[:, None]
    # a few projections far outside the queries' box land in the grid's border cells
    points[:20] = points[:20] * 1e4 - 5e4
    found = nearest_points(queries, points)
    distances = torch.cdist(queries.double(), points.double(), compute_mode="donot_use_mm_for_euclid_dist")
    nearest = distances.min(dim=1, keepdim=True).values
    lowest_tied = torch.where(distances == nearest, torch.arange(len(points)), len(points)).min(dim=1).values
    assert torch.equal(found, lowest_tied)
    assert (distances == nearest).sum() > len(queries)  # the case has ties


def test_nearest_points_with_every_point_far_outside_not_finite_or_none():
    queries = torch.tensor([[0.0, 0.0], [10.0, 5.0], [3.0, 3.0]])
    points = torch.tensor([[1e6, 1e6], [-2e5, 40.0], [5e3, -7e3], [30.0, -25.0]])
    distances = torch.cdist(queries.double(), points.double())
    assert torch.equal(nearest_points(queries, points), distances.argmin(dim=1))
    # a point that is not finite is never the nearest; without a finite point a query gets -1
    broken = torch.cat([torch.tensor([[math.nan, 0.0], [math.inf, 1.0]]), points])
    assert torch.equal(nearest_points(queries, broken), distances.argmin(dim=1) + 2)
    assert torch.equal(nearest_points(queries, broken[:2]), torch.full((3,), -1))
    assert torch.equal(nearest_points(queries, points[:0]), torch.full((3,), -1))
    with pytest.raises(ValueError, match="every query must be finite"):
        nearest_points(torch.tensor([[math.nan, 0.0]]), points)


def test_nearest_points_compare_in_the_wider_dtype():
    queries = torch.tensor([[1.0, 0.0]])  # float32
    points = torch.tensor([[1 + 2e-8, 0.0], [1 + 1e-8, 0.0]], dtype=torch.float64)
    assert nearest_points(queries, points).tolist() == [1]


def test_distance_loss_of_masks_continued_beyond_the_frame_reads_the_frames_own_pixels():
    """Continued masks hold a margin around the frame; the loss compares renders with the frame's part of it: for a
    mask clear of the border the continued and the plain distance transforms agree there."""
    masks = torch.zeros(2, 24, 32)
    masks[:, 8:16, 10:20] = 1
    alphas = torch.rand(2, 24, 32, generator=torch.Generator().manual_seed(0))
    views = torch.tensor([0, 1])
    plain = SilhouetteTargets(masks).distance_loss(alphas, views)
    continued = SilhouetteTargets(masks, continued_beyond_frame=True).distance_loss(alphas, views)
    assert plain > 0 and torch.allclose(continued, plain, rtol=1e-5, atol=0)


def _block_case(size=40, block=(10, 30)):
    """Targets of a [size, size] mask whose pixels block[0]..block[1] - 1 are set in both directions, and a camera
    at the world origin looking down +z with focal `size` and the principal point at the image centre."""
    masks = torch.zeros(1, size, size)
    masks[0, block[0]:block[1], block[0]:block[1]] = 1
    Ks = torch.tensor([[[float(size), 0, size / 2], [0, float(size), size / 2], [0, 0, 1]]])
    return SilhouetteTargets(masks), torch.eye(4)[None], Ks


def test_distance_loss_is_the_mean_of_alpha_times_the_euclidean_distance_to_the_mask():
    """One opaque pixel, (2, 5), outside a block mask whose nearest pixel is (10, 10): the loss is its Euclidean
    distance, sqrt(8^2 + 5^2) = 9.43 px (cv2's 5 x 5 approximation: 9.39), in image sizes, over the H W pixels.
    An L1 distance transform (13 px) or a sum over pixels instead of the mean passed every test."""
    targets, _, _ = _block_case()
    alphas = torch.zeros(1, 40, 40)
    alphas[0, 5, 2] = 1.0
    distance_px = targets.distance_loss(alphas, torch.tensor([0])).item() * 40 * 40 * 40
    assert distance_px == pytest.approx(math.hypot(8, 5), abs=0.1)


def test_chamfer_loss_is_the_weighted_distance_outside_the_mask_plus_the_edges_distance_to_the_solid_points():
    """The chamfer's value on a hand-made case: a 20 x 20 px block mask and four points, at (5.5, 20.5) (5 px left
    of the mask, weight 0.9), (20.5, 20.5) (inside, 0.5), (35, 12) (5.5 px right of it, 0.05: below the 0.1 cut-off
    of the edge side) and one behind the camera (0.9) whose meaningless pixel is the mask's corner. The point side is
    the weighted mean distance outside the mask of the points in front, (0.9 * 5 + 0.05 * 5.5) / 1.45 px; the edge
    side the mean, over the block's 76 border pixels, of the distance to the nearer of the two solid points in
    front; both in image sizes. Six mutants survived without it: the behind point in either side, no cut-off, the
    point side dropped, the edge side in pixels, the point side's mean unweighted."""
    targets, viewmats, Ks = _block_case()
    depth = 2.0
    in_front = [[(u - 20) * depth / 40, (v - 20) * depth / 40, depth] for u, v in ((5.5, 20.5), (20.5, 20.5), (35, 12))]
    behind = [(10.5 - 20) / 40, (10.5 - 20) / 40, -depth]  # `project_points` divides by 1 behind the camera
    points = torch.tensor([*in_front, behind])
    weights = torch.tensor([0.9, 0.5, 0.05, 0.9])
    value = targets.chamfer_loss(points, weights, viewmats, Ks, torch.tensor([0])).item()
    point_side = (0.9 * 5 + 0.05 * 5.5) / (0.9 + 0.5 + 0.05) / 40
    border = torch.tensor([[x + 0.5, y + 0.5] for y in range(10, 30) for x in range(10, 30) if {x, y} & {10, 29}])
    solid = torch.tensor([[5.5, 20.5], [20.5, 20.5]])
    edge_side = torch.cdist(border, solid).min(dim=1).values.mean().item() / 40
    assert len(border) == 76 and point_side > 0.05 and edge_side > 0.1
    assert value == pytest.approx(point_side + edge_side, abs=1e-6)


def test_chamfer_edge_pixels_are_spread_over_the_whole_contour():
    """More contour pixels than `EDGE_POINTS`: every k-th in raster order is kept, from the first row of the contour
    to its last, about half in each half of the image; the first 300 stopped at row 90 of a contour down to 179."""
    masks = torch.zeros(1, 200, 200)
    masks[0, 20:180, 20:180] = 1  # 636 contour pixels
    rows = SilhouetteTargets(masks).edges[0][:, 1]
    assert len(rows) == EDGE_POINTS and rows.min() == 20.5 and rows.max() == 179.5
    assert abs(int((rows < 100).sum()) - EDGE_POINTS // 2) <= 3


def test_object_radius_is_one_and_a_half_times_the_largest_half_extent_at_its_cameras_distance():
    """Two views of a block mask at the origin: a 20 px block (pixel centres 19 px apart) from 2 units away and a
    12 px one (11 px) from 4; focal 40 px. Half-extents in scene units are 9.5 / 40 * 2 = 0.475 and 5.5 / 40 * 4 =
    0.55: the radius is 1.5 * 0.55. The whole extent, another factor than 1.5, or one camera's distance for every
    view read otherwise."""
    masks = torch.zeros(2, 40, 40)
    masks[0, 10:30, 10:30] = 1
    masks[1, 14:26, 14:26] = 1
    viewmats = torch.eye(4).repeat(2, 1, 1)
    viewmats[0, 2, 3], viewmats[1, 2, 3] = 2.0, 4.0
    Ks = torch.tensor([[40.0, 0, 20], [0, 40, 20], [0, 0, 1]]).repeat(2, 1, 1)
    radius = SilhouetteTargets(masks).object_radius(viewmats, Ks, torch.zeros(3))
    assert radius == pytest.approx(1.5 * 5.5 / 40 * 4.0, rel=1e-6)


@pytest.mark.parametrize("samples", [95, 96])
def test_the_coherence_search_visits_the_first_and_last_samples_of_an_even_or_odd_count(samples):
    """The middle-out walk (kernels/coherence.py) must reach both ends of the depth range, for an even and an odd
    sample count: started on the other side, it skipped sample 0 of an even count, and no test had the least at an
    end. Camera 1 stands 0.01 past sample 0 of camera 0's ray facing back at camera 0 (or 0.01 before the last
    sample, facing the same way): that end alone is in front of it and on its mask, every other sample behind it."""
    masks = torch.zeros(2, 32, 32)
    masks[:, 12:20, 12:20] = 1
    targets = SilhouetteTargets(masks)
    Ks = torch.tensor([[50.0, 0, 16], [0, 50, 16], [0, 0, 1]], dtype=torch.float64).repeat(2, 1, 1)
    depths = torch.linspace(4.0, 6.0, samples, dtype=torch.float64)[None].repeat(2, 1)
    ray = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)  # camera 0's optical axis
    for end, (facing, at) in {0: (-1.0, 4.01), samples - 1: (1.0, 5.99)}.items():
        viewmats = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
        viewmats[1, 0, 0] = viewmats[1, 2, 2] = facing  # -1: turned half about y, looking down -z
        viewmats[1, 2, 3] = -facing * at  # centre at z = at
        chosen = least_outside_samples(ray, torch.zeros(1, dtype=torch.long), camera_centers(viewmats), depths,
                                       viewmats, Ks, targets.outside_distance, targets.margin, targets.size)
        assert chosen.tolist() == [end], (samples, end, chosen)


def test_the_coherence_search_reads_fx_fy_cx_cy_each_in_its_own_place():
    """Every coherence test had square images, fx == fy and the principal point in the middle: the search reading
    cx for cy, fx for fy, or the wrapper passing cx and cy swapped all passed. With 48 x 32 images, fx != fy and a
    principal point off the middle, the search still picks on each ray a least sample of the torch charge
    (`_outside_other_views`), which projects with `project_points`."""
    width, height = 48, 32
    eyes = torch.tensor([[4.0, 0.3, 0.5], [0.4, 4.0, 0.8], [-3.0, -2.5, 1.2], [0.5, -0.3, 4.0]])
    viewmats = torch.stack([look_at(eye, torch.zeros(3)) for eye in eyes])
    K = torch.tensor([[55.0, 0.0, 27.0], [0.0, 40.0, 13.0], [0.0, 0.0, 1.0]])
    ys, xs = torch.meshgrid(torch.arange(float(height)) + 0.5, torch.arange(float(width)) + 0.5, indexing="ij")
    pixels = torch.stack([xs, ys], -1).reshape(-1, 2)
    half_extent = torch.tensor([0.6, 0.4, 0.5])
    masks = []
    for viewmat, eye in zip(viewmats, eyes):  # the box's silhouettes: pixels whose rays meet it (the slab test)
        rays = pixel_directions(pixels, K) @ viewmat[:3, :3]
        enter, leave = (-half_extent - eye) / rays, (half_extent - eye) / rays
        near, far = torch.minimum(enter, leave).amax(-1), torch.maximum(enter, leave).amin(-1)
        masks.append(((near <= far) & (far > 0)).float().reshape(height, width))
    targets = SilhouetteTargets(torch.stack(masks))
    viewmats = perturb_viewmats(viewmats.double(), 4.0, 0.1, seed=0)  # silhouettes that disagree a little
    Ks = K.double().expand(len(eyes), 3, 3)
    centers = camera_centers(viewmats)
    depths = centers.norm(dim=-1)[:, None] + torch.linspace(-1.0, 1.0, 96, dtype=torch.float64)
    for view in range(len(viewmats)):
        rays = pixel_directions(targets.foreground[view].double(), Ks[view]) @ viewmats[view, :3, :3]
        chosen = least_outside_samples(rays, torch.full((len(rays),), view), centers, depths, viewmats, Ks,
                                       targets.outside_distance, targets.margin, targets.size)
        points = centers[view] + rays[:, None] * depths[view][None, :, None]
        totals = targets._outside_other_views(points.reshape(-1, 3), view, viewmats, Ks).reshape(points.shape[:2])
        torch.testing.assert_close(totals.gather(1, chosen[:, None])[:, 0], totals.min(dim=1).values,
                                   rtol=0, atol=1e-12)
