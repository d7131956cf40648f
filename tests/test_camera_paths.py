"""warpbags.camera_paths: turntables, azimuth order and cameras between neighbours (CPU, float64)."""

from __future__ import annotations

import math

import torch
from random_poses import F64

from warpbags.camera_paths import azimuth_order, interpolated_viewmats, turntable_viewmats
from warpbags.cameras import camera_centers
from warpbags.lie import rotation_error_deg, so3_exp

def test_interpolated_viewmats_walk_the_orbit_between_neighbouring_cameras():
    base = torch.eye(4, dtype=F64)
    base[2, 3] = 4.0
    orbit = turntable_viewmats(base[None], 16)
    shuffled = orbit[::2][torch.tensor([3, 0, 6, 1, 5, 2, 7, 4])]  # 8 cameras 45 degrees apart, out of order
    order = azimuth_order(shuffled)
    assert len(set(order.tolist())) == 8
    # Neighbours in azimuth order are 45 degrees apart (2 turntable steps of 16).
    angles = rotation_error_deg(shuffled[order, :3, :3], shuffled[order.roll(-1), :3, :3])
    torch.testing.assert_close(angles, torch.full((8,), 45.0, dtype=F64))
    ends = interpolated_viewmats(shuffled, torch.tensor([0, 5]), torch.tensor([0.0, 1.0], dtype=F64))
    torch.testing.assert_close(ends, shuffled[order[[0, 6]]], rtol=0, atol=1e-12)
    middles = interpolated_viewmats(shuffled, torch.arange(8), torch.full((8,), 0.5, dtype=F64))
    # Each midpoint is an odd turntable frame (the frames between the even ones), each found exactly once.
    distances = torch.cdist(middles[:, :3, :].flatten(1), orbit[1::2, :3, :].flatten(1))
    assert distances.min(dim=1).values.max().item() < 1e-9
    assert sorted(distances.argmin(dim=1).tolist()) == list(range(8))
    quarter = interpolated_viewmats(shuffled, torch.arange(8), torch.full((8,), 0.25, dtype=F64))
    torch.testing.assert_close(camera_centers(quarter).norm(dim=-1), torch.full((8,), 4.0, dtype=F64))


def test_the_up_axis_of_cameras_on_one_side_of_the_object_is_level():
    """Cameras on an arc of +-30 deg, looking down 30 deg at the object: their mean up leaned 28 deg towards them and
    half of a turntable went under the object. The common up is world z; a lone camera keeps its own up."""
    from conftest import look_at

    from warpbags.camera_paths import mean_up_axis

    eyes = [torch.tensor([4 * math.cos(math.radians(a)), 4 * math.sin(math.radians(a)), 4 * math.tan(math.radians(30))],
                         dtype=F64) for a in (-30, -15, 0, 15, 30)]
    viewmats = torch.stack([look_at(eye, torch.zeros(3, dtype=F64)) for eye in eyes])
    torch.testing.assert_close(mean_up_axis(viewmats), torch.tensor([0.0, 0.0, 1.0], dtype=F64), rtol=0, atol=1e-9)
    turntable = turntable_viewmats(viewmats, 8)
    heights = camera_centers(turntable)[:, 2]
    torch.testing.assert_close(heights, heights[:1].expand(8))  # the orbit stays at the cameras' height
    torch.testing.assert_close(mean_up_axis(viewmats[:1]), -viewmats[0, 1, :3], rtol=0, atol=1e-12)


def test_the_up_axis_of_cameras_rolled_by_a_quarter_turn_is_still_level():
    """Portrait photos stored sideways (a phone's EXIF rotation, not applied) are cameras rolled by 90 deg: their x
    axes lean towards the object and the axis perpendicular to them was horizontal, so the turntable tumbled under
    the object and the viewer opened sideways. Their y axes are level: the up is still world z, either way rolled."""
    from conftest import look_at

    from warpbags.camera_paths import mean_up_axis

    eyes = [torch.tensor([4 * math.cos(math.radians(a)), 4 * math.sin(math.radians(a)), 2.3], dtype=F64)
            for a in range(0, 360, 45)]
    upright = torch.stack([look_at(eye, torch.zeros(3, dtype=F64)) for eye in eyes])
    for roll in (90.0, -90.0, 0.0):
        turn = torch.eye(4, dtype=F64)
        turn[:3, :3] = so3_exp(torch.tensor([0.0, 0.0, math.radians(roll)], dtype=F64))  # about each optical axis
        rolled = turn @ upright
        torch.testing.assert_close(mean_up_axis(rolled), torch.tensor([0.0, 0.0, 1.0], dtype=F64), rtol=0, atol=1e-9)
        heights = camera_centers(turntable_viewmats(rolled, 8))[:, 2]
        torch.testing.assert_close(heights, torch.full((8,), 2.3, dtype=F64))


def test_cameras_between_neighbours_on_a_ring_look_at_the_object():
    """On a ring looking down at the object, the slerped orientation turns about one axis while the centre rises
    along the great circle: the camera between two of 4 views looked 9 deg past the object, between 2 views 60."""
    from conftest import look_at

    for count in (2, 3, 4):
        eyes = [torch.tensor([4 * math.cos(2 * math.pi * k / count), 4 * math.sin(2 * math.pi * k / count),
                              4 * math.tan(math.radians(30))], dtype=F64) for k in range(count)]
        viewmats = torch.stack([look_at(eye, torch.zeros(3, dtype=F64)) for eye in eyes])
        between = interpolated_viewmats(viewmats, torch.arange(count), torch.full((count,), 0.5, dtype=F64))
        to_object = (between[:, :3, :3] @ -camera_centers(between)[..., None])[..., 0]
        off_axis = torch.rad2deg(torch.atan2(to_object[:, :2].norm(dim=-1), to_object[:, 2]))
        assert off_axis.max() < 1e-6, (count, off_axis)


def test_a_turntable_turns_about_the_object_centre_it_is_given():
    """Cameras around an object 0.9 units off the origin (a run trained from noisy poses puts its Gaussians off it):
    the turntable turned about the origin, and the object swung across the frames. About the object's centre, every
    frame sees it where camera 0 does, from camera 0's distance and height."""
    from conftest import look_at

    center = torch.tensor([0.5, -0.6, 0.4], dtype=F64)
    eyes = [center + torch.tensor([4 * math.cos(a), 4 * math.sin(a), 1.5], dtype=F64) for a in (0.3, 1.9, 3.6, 5.0)]
    viewmats = torch.stack([look_at(eye, center) for eye in eyes])
    turntable = turntable_viewmats(viewmats, 8, center)
    torch.testing.assert_close(turntable[0], viewmats[0], rtol=0, atol=1e-12)
    seen = turntable[:, :3, :3] @ center + turntable[:, :3, 3]  # the centre in each frame's camera axes
    torch.testing.assert_close(seen, seen[:1].expand(8, 3), rtol=0, atol=1e-12)
    offsets = camera_centers(turntable) - center
    torch.testing.assert_close(offsets[:, 2], torch.full((8,), 1.5, dtype=F64))  # world z up: at camera 0's height
    torch.testing.assert_close(offsets[4, :2], -offsets[0, :2])  # half a turn later: the opposite side


def test_cameras_between_neighbours_of_an_object_off_the_origin_turn_about_it():
    """The repair stage's pseudo views were slerped about the origin: around Gaussians that noisy poses left 0.4
    units off it, they saw the object 8-50 px of 128 off where their neighbours do. About the object's centre, the
    in-between cameras of a rig moved off the origin are those of the rig at the origin, moved alike."""
    from conftest import look_at

    center = torch.tensor([0.5, -0.6, 0.4], dtype=F64)
    eyes = [torch.tensor([4 * math.cos(a), 4 * math.sin(a), 1.5], dtype=F64) for a in (0.3, 1.9, 3.6, 5.0)]
    at_origin = torch.stack([look_at(eye, torch.zeros(3, dtype=F64)) for eye in eyes])
    moved = torch.eye(4, dtype=F64)
    moved[:3, 3] = -center  # world points x + center of the moved rig are the points x of the rig at the origin
    gaps, fractions = torch.tensor([0, 1, 2, 3]), torch.tensor([0.5, 0.3, 0.7, 0.5], dtype=F64)
    expected = interpolated_viewmats(at_origin, gaps, fractions) @ moved
    torch.testing.assert_close(interpolated_viewmats(at_origin @ moved, gaps, fractions, center), expected,
                               rtol=0, atol=1e-12)
    seen = expected[:, :3, :3] @ center + expected[:, :3, 3]  # the object's centre in each camera: on its axis
    torch.testing.assert_close(seen[:, :2], torch.zeros(4, 2, dtype=F64), rtol=0, atol=1e-9)


def _ring(azimuths_deg, radii, height=0.0):
    """[C, 4, 4] cameras at `azimuths_deg` about world z, `radii` from its axis, `height` above the origin, each
    looking at the origin."""
    from conftest import look_at

    eyes = [torch.tensor([r * math.cos(math.radians(a)), r * math.sin(math.radians(a)), height], dtype=F64)
            for a, r in zip(azimuths_deg, radii)]
    return torch.stack([look_at(eye, torch.zeros(3, dtype=F64)) for eye in eyes])


def test_cameras_between_two_opposite_cameras_go_round_the_object_at_their_height():
    """Two cameras exactly opposite across the centre have no great circle: the mixed direction was the zero vector
    and the camera half-way NaN; a hair above level (1e-9) it went over the top of the object, a hair below under
    it. Half-way along each gap, the camera is 90 deg round in azimuth (the gap's way), at the cameras' height and
    distance, upright and looking at the centre; the gap's ends are its cameras, turned off the centre or not."""
    from conftest import look_at

    for height in (0.0, 1e-9, -1e-9, 0.2):
        eyes = torch.tensor([[4.0, 0.0, height], [-4.0, 0.0, height]], dtype=F64)  # exactly opposite
        viewmats = torch.stack([look_at(eye, torch.zeros(3, dtype=F64)) for eye in eyes])
        order = azimuth_order(viewmats)
        between = interpolated_viewmats(viewmats, torch.tensor([0, 1]), torch.full((2,), 0.5, dtype=F64))
        assert torch.isfinite(between).all(), height
        centers = camera_centers(between)
        azimuths = torch.rad2deg(torch.atan2(centers[:, 1], centers[:, 0]))
        first = torch.rad2deg(torch.atan2(eyes[order, 1], eyes[order, 0]))  # the gaps' first cameras
        torch.testing.assert_close((azimuths - first) % 360, torch.full((2,), 90.0, dtype=F64), rtol=0, atol=1e-9)
        torch.testing.assert_close(centers[:, 2], torch.full((2,), height, dtype=F64), rtol=0, atol=1e-9)
        torch.testing.assert_close(centers[:, :2].norm(dim=-1), torch.full((2,), 4.0, dtype=F64), rtol=0, atol=1e-9)
        to_object = (between[:, :3, :3] @ -centers[..., None])[..., 0]  # the centre in camera axes: straight ahead
        torch.testing.assert_close(to_object / to_object.norm(dim=-1, keepdim=True),
                                   torch.tensor([[0.0, 0.0, 1.0]] * 2, dtype=F64), rtol=0, atol=1e-9)
        assert (-between[:, 1, 2] > 0.99).all(), (height, between[:, 1])  # the camera's up (-y) is world z
    viewmats = _ring([0.0, 180.0], [4.0, 4.0], 0.3)
    viewmats[:, :3, :] = so3_exp(torch.tensor([[0.1, -0.05, 0.0], [0.0, 0.2, 0.1]], dtype=F64)) @ viewmats[:, :3, :]
    order = azimuth_order(viewmats)
    ends = interpolated_viewmats(viewmats, torch.tensor([0, 1, 0, 1]), torch.tensor([0.0, 0.0, 1.0, 1.0], dtype=F64))
    torch.testing.assert_close(ends, viewmats[torch.cat([order, order.roll(-1)])], rtol=0, atol=1e-9)


def test_the_distance_to_the_centre_is_interpolated_from_the_first_camera_to_the_second():
    """The distances' weights swapped ((1 - s) on the second camera) passed every test whose cameras share one
    distance: between a camera 3 from the centre and one 5 from it, a quarter of the way is 3.5 from it."""
    viewmats = _ring([0.0, 90.0, 180.0, 270.0], [3.0, 5.0, 3.0, 5.0], height=1.0)
    order = azimuth_order(viewmats)
    between = interpolated_viewmats(viewmats, torch.arange(4), torch.full((4,), 0.25, dtype=F64))
    first = camera_centers(viewmats[order]).norm(dim=-1)
    second = camera_centers(viewmats[order.roll(-1)]).norm(dim=-1)
    torch.testing.assert_close(camera_centers(between).norm(dim=-1), 0.75 * first + 0.25 * second,
                               rtol=0, atol=1e-12)


def test_a_gaps_ends_are_its_two_cameras_even_when_they_do_not_look_at_the_centre():
    """The re-aim's target taken from the first camera alone passed while every camera looked at the centre; cameras
    turned off it (as noisy poses are) must still be reproduced at fractions 0 and 1."""
    viewmats = _ring([0.0, 80.0, 170.0, 260.0], [4.0] * 4, height=1.5)
    turns = so3_exp(torch.tensor([[0.1, -0.05, 0.0], [0.0, 0.2, 0.1], [-0.15, 0.0, 0.05], [0.05, 0.1, -0.1]],
                                 dtype=F64))
    viewmats[:, :3, :] = turns @ viewmats[:, :3, :]  # each camera turned about its centre
    order = azimuth_order(viewmats)
    ends = interpolated_viewmats(viewmats, torch.tensor([0, 1, 2, 3, 0, 1, 2, 3]),
                                 torch.tensor([0.0] * 4 + [1.0] * 4, dtype=F64))
    torch.testing.assert_close(ends, viewmats[torch.cat([order, order.roll(-1)])], rtol=0, atol=1e-9)


def test_cameras_between_two_at_a_right_angle_are_spaced_evenly_along_the_arc():
    """Normalized linear interpolation of the directions (slerp's weights never used) bunched the cameras towards
    the middle of the arc (a quarter of the way at 18.4 deg); slerp spaces them evenly: a quarter of a 90 deg gap
    is 22.5 deg."""
    viewmats = _ring([0.0, 90.0, 180.0, 270.0], [4.0] * 4)
    between = camera_centers(interpolated_viewmats(viewmats, torch.arange(4), torch.full((4,), 0.25, dtype=F64)))
    azimuths = torch.rad2deg(torch.atan2(between[:, 1], between[:, 0])) % 90
    torch.testing.assert_close(azimuths, torch.full((4,), 22.5, dtype=F64), rtol=0, atol=1e-6)


def test_the_common_up_is_signed_as_the_cameras_up_in_a_turned_world():
    """The eigenvector of the x axes comes with either sign; left as eigh returns it, it passed while that happened
    to be +z. With the world turned about x (by up to half a turn), the up is the turned z."""
    from conftest import look_at

    from warpbags.camera_paths import mean_up_axis

    eyes = [torch.tensor([4 * math.cos(math.radians(a)), 4 * math.sin(math.radians(a)), 1.5], dtype=F64)
            for a in (-30, -15, 0, 15, 30)]
    viewmats = torch.stack([look_at(eye, torch.zeros(3, dtype=F64)) for eye in eyes])
    for angle in (0.0, 0.7, 2.0, math.pi):
        turn = torch.eye(4, dtype=F64)
        turn[:3, :3] = so3_exp(torch.tensor([angle, 0.0, 0.0], dtype=F64))  # point y here: turn @ y before
        expected = turn[:3, :3].T @ torch.tensor([0.0, 0.0, 1.0], dtype=F64)
        torch.testing.assert_close(mean_up_axis(viewmats @ turn), expected, rtol=0, atol=1e-9)
