"""Initial points: random points say when the cameras share too little of the scene to keep only what they see."""

from __future__ import annotations

import pytest
import torch
from conftest import look_at

from warpbags.cameras import pixel_directions, project_points
from warpbags.init import hull_or_random_points, initial_gaussians, point_colors, visual_hull
from warpbags.kernels.sh import SH_C0
from warpbags.wrapper import mean_neighbour_distances

WIDTH = HEIGHT = 32
RED = torch.tensor([0.8, 0.1, 0.1])  # the object's colour in `_red_sphere_on_white`
KS = torch.tensor([[40.0, 0.0, 16.0], [0.0, 40.0, 16.0], [0.0, 0.0, 1.0]]).expand(2, 3, 3)


def _random_points(viewmats: torch.Tensor) -> tuple[torch.Tensor, str]:
    images = torch.zeros(len(viewmats), HEIGHT, WIDTH, 3)
    points, _, note = hull_or_random_points(images, None, viewmats, KS, method="random", count=200, resolution=8,
                                            dilation_px=0, missed_views=1, generator=torch.Generator().manual_seed(0))
    return points, note


def test_random_points_are_seen_by_every_camera_when_enough_are():
    eyes = torch.tensor([[4.0, 0.0, 0.5], [0.0, 4.0, 0.5]])
    viewmats = torch.stack([look_at(eye, torch.zeros(3)) for eye in eyes])
    points, note = _random_points(viewmats)
    assert note == "random points (200)"
    pixels, depths = project_points(viewmats, KS, points)
    assert (depths > 0).all() and ((pixels >= 0) & (pixels < WIDTH)).all()  # inside both images


def test_random_points_say_so_when_no_region_is_seen_by_every_camera():
    # Two cameras at the origin looking in opposite directions share nothing of the cube.
    eyes = torch.zeros(2, 3)
    viewmats = torch.stack([look_at(eyes[0], torch.tensor([1.0, 0.0, 0.0])),
                            look_at(eyes[1], torch.tensor([-1.0, 0.0, 0.0]))])
    points, note = _random_points(viewmats)
    assert len(points) == 200
    assert note == ("random points (200); only 0 of 1600 drawn points are seen by every camera, so they come from "
                    "the whole cube")


def test_mean_neighbour_distances_is_the_brute_force_mean():
    points = torch.rand(300, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    for k in (1, 17):
        brute = torch.cdist(points, points).sort(dim=1).values[:, 1:k + 1].mean(1)
        found = mean_neighbour_distances(points, k)
        assert found.dtype == torch.float64
        torch.testing.assert_close(found, brute, rtol=0, atol=1e-12)


def _brute_mean_distances(points: torch.Tensor, k: int) -> torch.Tensor:
    return torch.cdist(points.double(), points.double()).sort(dim=1).values[:, 1:k + 1].mean(1)


def test_mean_neighbour_distances_is_exact_on_a_surface_with_far_floaters_and_duplicates():
    """The floater removal's case: points on a sphere's surface (most grid cells empty), a few floaters hundreds of
    radii away (clamped into the grid's border cells), and duplicated points (distance 0); k = sqrt(P) as the
    removal takes it, 1, and every other point. float32 points are measured in float64 as well."""
    generator = torch.Generator().manual_seed(3)
    surface = torch.randn(600, 3, generator=generator)
    surface = surface / surface.norm(dim=1, keepdim=True)
    floaters = torch.tensor([[300.0, 0.0, 0.0], [-250.0, 80.0, 5.0], [0.5, 0.5, 400.0]])
    points = torch.cat([surface, floaters, surface[:20]]).float()
    for k in (1, int(len(points) ** 0.5), len(points) - 1):
        found = mean_neighbour_distances(points, k)
        assert found.dtype == torch.float32
        torch.testing.assert_close(found.double(), _brute_mean_distances(points, k), rtol=1e-6, atol=0)
    assert (mean_neighbour_distances(points, 1)[-20:] == 0).all()  # each duplicate's nearest is its twin


def test_mean_neighbour_distances_rejects_what_it_cannot_measure():
    points = torch.rand(10, 3)
    for k in (0, 10):
        with pytest.raises(ValueError, match=f"k must be in \\[1, 9\\] for 10 points, got {k}"):
            mean_neighbour_distances(points, k)
    points[4, 1] = float("nan")
    with pytest.raises(ValueError, match="every point must be finite"):
        mean_neighbour_distances(points, 3)


def _silhouettes(eyes: torch.Tensor, hits, size: int = 64):
    """Cameras at `eyes` looking at the origin, and in each the silhouette of the pixels whose ray (from `eye`, along
    [P, 3] `rays`) `hits(eye, rays)` says meets the object."""
    viewmats = torch.stack([look_at(eye, torch.zeros(3)) for eye in eyes])
    Ks = torch.tensor([[60.0, 0.0, size / 2], [0.0, 60.0, size / 2], [0.0, 0.0, 1.0]]).expand(len(eyes), 3, 3)
    ys, xs = torch.meshgrid(torch.arange(float(size)) + 0.5, torch.arange(float(size)) + 0.5, indexing="ij")
    masks = []
    for viewmat, K, eye in zip(viewmats, Ks, eyes):
        rays = pixel_directions(torch.stack([xs, ys], -1).reshape(-1, 2), K) @ viewmat[:3, :3]
        masks.append(hits(eye, rays).float().reshape(size, size))
    return viewmats, Ks, torch.stack(masks)


def _sphere_silhouettes(eyes: torch.Tensor, size: int = 64):
    """The unit sphere's silhouettes (`_silhouettes`): rays that pass within 1 of the origin."""
    def hits(eye, rays):
        rays = rays / rays.norm(dim=-1, keepdim=True)
        along = -(eye * rays).sum(-1)
        return (eye + along[:, None] * rays).norm(dim=-1) < 1.0
    return _silhouettes(eyes, hits, size)


def test_the_masks_dilation_widens_the_hull_to_hold_what_slightly_wrong_poses_carve_off():
    """The quick preset dilates every mask by 2 px before carving (`hull_dilation_px`), so that a hull carved at
    poses a few pixels off still holds the object; no test passed a dilation (skipping it passed)."""
    eyes = torch.tensor([[4.0, 0.0, 0.0], [0.0, 4.0, 0.0], [0.0, 0.0, 4.0]])
    viewmats, Ks, masks = _sphere_silhouettes(eyes)
    shifted = masks.roll(3, dims=2)  # one view's silhouette 3 px off, as a pose a little off would put it
    masks = torch.stack([masks[0], shifted[1], masks[2]])
    plain, edge = visual_hull(masks, viewmats, Ks, resolution=32, dilation_px=0, missed_views=0)
    dilated, _ = visual_hull(masks, viewmats, Ks, resolution=32, dilation_px=3, missed_views=0)
    sphere = torch.randn(2000, 3, generator=torch.Generator().manual_seed(0))
    sphere = 0.9 * sphere / sphere.norm(dim=-1, keepdim=True)  # points just inside the object's surface
    held = [float((torch.cdist(sphere, voxels).min(dim=1).values < edge).float().mean()) for voxels in (plain, dilated)]
    assert held[0] < 0.97 and held[1] > 0.99, held


def test_a_two_view_hull_is_the_intersection_of_the_silhouettes():
    """With 2 views the default one missed view kept every voxel inside either silhouette: the union, each view's
    cone out to the cube's walls (85% of the hull outside a sphere). Two views must agree, as one holds no depth."""
    viewmats, Ks, masks = _sphere_silhouettes(torch.tensor([[4.0, 0.0, 0.0], [0.0, 4.0, 0.0]]))
    voxels, edge = visual_hull(masks, viewmats, Ks, resolution=32, dilation_px=0, missed_views=1)
    inside = (voxels.norm(dim=-1) < 1.0 + edge).float().mean()
    assert len(voxels) > 100 and inside > 0.5, (len(voxels), float(inside))


def test_silhouettes_that_share_no_volume_give_random_points_and_say_so():
    """Masks that no point is inside in both views (each the opposite half of its image) carve an empty hull:
    random points, with the note saying how many voxels the hull had (the empty hull's early return was untested;
    without it the fine pass took the bounds of no voxels, an IndexError)."""
    eyes = torch.tensor([[4.0, 0.0, 0.0], [-4.0, 0.0, 0.0]])  # facing each other: left in one is right in the other
    viewmats = torch.stack([look_at(eye, torch.zeros(3)) for eye in eyes])
    masks = torch.zeros(2, HEIGHT, WIDTH)
    masks[:, :, : WIDTH // 2 - 2] = 1.0  # the left part of both images: disjoint half-spaces of the world
    voxels, _ = visual_hull(masks, viewmats, KS, resolution=16, dilation_px=0, missed_views=0)
    assert len(voxels) == 0
    points, colors, note = hull_or_random_points(torch.zeros(2, HEIGHT, WIDTH, 3), masks, viewmats, KS, method="hull",
                                                 count=150, resolution=16, dilation_px=0, missed_views=0,
                                                 generator=torch.Generator().manual_seed(0))
    assert note.startswith("visual hull had only 0 voxels; random points instead (150)") and points.shape == (150, 3)
    assert colors.shape == (150, 3)


def _red_sphere_on_white():
    """Three views (along x, y and z) of the unit sphere, red on a white background: images, masks, viewmats, Ks."""
    viewmats, Ks, masks = _sphere_silhouettes(torch.tensor([[4.0, 0.0, 0.0], [0.0, 4.0, 0.0], [0.0, 0.0, 4.0]]), 48)
    images = torch.ones(*masks.shape, 3)
    images[masks.bool()] = RED
    return images, masks, viewmats, Ks


def test_hull_points_take_the_objects_colour_in_rgb_order():
    """A point's colour is its mean over the views that see it inside the mask: every point of a red object's hull is
    that red, in RGB order. The hull is carved from masks dilated by 2 px, so points near its edge fall on the white
    background in some views; the masks themselves keep those views out of the mean."""
    images, masks, viewmats, Ks = _red_sphere_on_white()
    points, colors, note = hull_or_random_points(images, masks, viewmats, Ks, method="hull", count=300, resolution=24,
                                                 dilation_px=2, missed_views=0,
                                                 generator=torch.Generator().manual_seed(0))
    assert note.startswith("visual hull: ") and points.shape == colors.shape == (300, 3), note
    torch.testing.assert_close(colors, RED.expand(300, 3), rtol=0, atol=1e-6)


@pytest.mark.parametrize("opacity, given", [(0.1, {}), (0.3, {"opacity": 0.3})], ids=["default", "given"])
def test_initial_gaussians_hold_the_given_opacity_and_colours(opacity, given):
    """Opacities are stored as logits and colours as the DC SH coefficient (colour = SH_C0 * sh0 + 0.5): both must
    read back as given (3DGS starts at opacity 0.1; a flipped logit starts every Gaussian at 0.9)."""
    points = torch.rand(40, 3, generator=torch.Generator().manual_seed(1))
    colors = torch.rand(40, 3, generator=torch.Generator().manual_seed(2))
    params = initial_gaussians(points, colors, 0, **given)
    torch.testing.assert_close(torch.sigmoid(params["opacities"]), torch.full((40,), opacity), rtol=0, atol=1e-6)
    torch.testing.assert_close(SH_C0 * params["sh0"][:, 0] + 0.5, colors, rtol=0, atol=1e-6)
    torch.testing.assert_close(params["means"], points)


def test_sfm_points_keep_their_own_colours():
    """SfM initialization subsamples the points at random: each picked point must bring its own colour along (here
    a colour that is a function of the point, so a mismatch shows)."""
    generator = torch.Generator().manual_seed(0)
    sfm_points = torch.randn(60, 3, generator=generator, dtype=torch.float64)
    sfm_colors = torch.sigmoid(sfm_points)  # each point's colour, from its coordinates
    images = torch.zeros(2, HEIGHT, WIDTH, 3)
    viewmats = torch.stack([look_at(eye, torch.zeros(3)) for eye in torch.tensor([[4.0, 0.0, 0.5], [0.0, 4.0, 0.5]])])
    points, colors, note = hull_or_random_points(images, None, viewmats, KS, method="sfm", count=25, resolution=8,
                                                 dilation_px=0, missed_views=1, generator=generator,
                                                 sfm_points=sfm_points, sfm_colors=sfm_colors)
    assert note == "SfM points: 25 of 60" and points.shape == colors.shape == (25, 3)
    assert torch.cdist(points.double(), sfm_points).min(dim=1).values.max() < 1e-6  # the scene's points, no others
    torch.testing.assert_close(colors, torch.sigmoid(points.double()).float(), rtol=0, atol=1e-6)


def test_initial_scales_are_the_log_of_the_mean_distance_to_the_three_nearest_points():
    """Nothing read the initial scales back: the 4 nearest points instead of 3, or the scales stored without their
    log, passed. Each Gaussian starts round, its log scale the log of its brute-force mean distance to the 3 nearest
    other points; the higher SH coefficients, one row per basis function past the DC, start at zero."""
    points = torch.rand(50, 3, generator=torch.Generator().manual_seed(0))
    brute = _brute_mean_distances(points, 3)
    for degree in (0, 1, 3):
        params = initial_gaussians(points, torch.rand(50, 3), degree)
        torch.testing.assert_close(params["scales"].double(), brute.log()[:, None].expand(50, 3), rtol=0, atol=1e-5)
        if degree == 0:
            assert "shN" not in params
        else:
            assert params["shN"].shape == (50, (degree + 1) ** 2 - 1, 3) and not params["shN"].any(), degree


def _box_silhouettes(eyes: torch.Tensor, half_extent: torch.Tensor, size: int = 64):
    """The silhouettes of the box [-half_extent, half_extent] (`_silhouettes`): rays that meet it (the slab test)."""
    def hits(eye, rays):
        enter, leave = (-half_extent - eye) / rays, (half_extent - eye) / rays
        near, far = torch.minimum(enter, leave).amax(-1), torch.maximum(enter, leave).amin(-1)
        return (near <= far) & (far > 0)
    return _silhouettes(eyes, hits, size)


def test_the_hull_of_an_elongated_object_reaches_both_of_its_ends():
    """The fine pass carves a cube around the coarse pass's box, sized by that box's longest side: sized by its
    shortest, it cut a 3 x 0.6 x 0.6 object down to a 0.6 cube and passed every test of round objects."""
    eyes = torch.tensor([[0.3, 5.0, 0.4], [0.4, 0.3, 5.0], [5.0, 0.3, 0.4], [-3.5, 3.5, 1.0]])
    viewmats, Ks, masks = _box_silhouettes(eyes, torch.tensor([1.5, 0.3, 0.3]))
    voxels, _ = visual_hull(masks, viewmats, Ks, resolution=32, missed_views=0)
    assert voxels[:, 0].max() > 1.4 and voxels[:, 0].min() < -1.4, (voxels[:, 0].min(), voxels[:, 0].max())


def test_a_point_no_view_sees_inside_its_mask_is_grey():
    """A point's colour is its mean over the views that see it inside the mask; one that no view sees inside is the
    documented 0.5 grey (black passed), while one inside the object takes its views' colours."""
    eyes = torch.tensor([[4.0, 0.0, 0.0], [0.0, 4.0, 0.0]])
    viewmats, Ks, masks = _box_silhouettes(eyes, torch.tensor([0.5, 0.5, 0.5]))
    images = torch.rand(2, 64, 64, 3, generator=torch.Generator().manual_seed(0))
    points = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.5]])  # inside the box; above it, off both masks
    colors = point_colors(points, images, masks, viewmats, Ks)
    torch.testing.assert_close(colors[1], torch.full((3,), 0.5), rtol=0, atol=0)
    seen = torch.stack([images[0, 32, 32], images[1, 32, 32]]).mean(0)  # the origin is each image's centre pixel
    torch.testing.assert_close(colors[0], seen, rtol=0, atol=1e-6)


def test_a_hull_of_exactly_min_voxels_is_kept_and_one_voxel_fewer_is_not():
    """The hull is used when it has at least `min_voxels` voxels, else random points: the cut-off was never tested
    at its edge (ten times the threshold passed)."""
    eyes = torch.tensor([[4.0, 0.0, 0.0], [0.0, 4.0, 0.0], [0.0, 0.0, 4.0]])
    viewmats, Ks, masks = _box_silhouettes(eyes, torch.tensor([0.3, 0.3, 0.3]))
    voxels, _ = visual_hull(masks, viewmats, Ks, resolution=8, missed_views=0)
    images = torch.rand(3, 64, 64, 3, generator=torch.Generator().manual_seed(0))
    notes = [hull_or_random_points(images, masks, viewmats, Ks, method="hull", count=50, resolution=8, dilation_px=0,
                                   missed_views=0, generator=torch.Generator().manual_seed(0),
                                   min_voxels=len(voxels) + extra)[2] for extra in (0, 1)]
    assert notes[0].startswith(f"visual hull: {len(voxels)} voxels") and notes[1].startswith(
        f"visual hull had only {len(voxels)} voxels"), notes
