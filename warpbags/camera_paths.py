"""Camera paths around an object: the cameras' mean up axis, turntables, azimuth order, in-between cameras.

Used for rendered videos (turntable) and the repair stage's pseudo views (cameras between neighbouring training
cameras). Both turn about a given object centre (the Gaussians'), by default the world origin, the object centre of a
normalized scene at its true poses. Poses follow `warpbags.cameras`' conventions.
"""

from __future__ import annotations

import math

import torch

from warpbags.cameras import camera_centers, viewmats_from_centers
from warpbags.lie import rotation_between, so3_exp, so3_log

__all__ = ["azimuth_order", "interpolated_viewmats", "mean_up_axis", "turntable_viewmats"]

# Gaps whose cameras are more nearly opposite than this (their angle about the centre) turn about the cameras' common
# up, not along their great circle: within 10 deg of opposite, the circle's elevation half-way moves 11 times or more
# as far as the cameras' elevations do (a hair above level, it ran over the object; below, under it), and exactly
# opposite there is no circle.
OPPOSITE_GAP_DEG = 170.0


def mean_up_axis(viewmats: torch.Tensor) -> torch.Tensor:
    """[3] unit world direction of the cameras' common "up": the direction most nearly perpendicular to every
    camera's x axis (rows of R are the camera axes), signed as their mean up (-y of OpenCV axes).

    Cameras are seldom rolled, so their x axes are level whichever way they look, while their up axes lean towards
    the object: averaged, those of cameras on one side of it (an arc of +-30 deg looking down 30 deg) tilt the mean
    28 deg and the turntable goes under the object. Where the x axes do not single a direction out (one camera, or
    all of them side by side), the mean up itself. Cameras rolled by 90 deg (portrait photos stored sideways, as
    phones store them with an EXIF rotation that is not applied) have level y axes instead: where the y axes lie
    clearly closer to one plane than the x axes, its normal is the up, signed so that the cameras look down at the
    object on average (or, looking level, sit above it).
    """
    mean_up = -viewmats[:, 1, :3].mean(0)
    x_axes, y_axes = viewmats[:, 0, :3], viewmats[:, 1, :3]
    values, vectors = torch.linalg.eigh(x_axes.T @ x_axes)  # ascending
    if values[1] < 0.01 * values[2]:  # the x axes within ~6 deg of one line: every normal to it is level
        return mean_up / mean_up.norm().clamp_min(1e-12)
    up = vectors[:, 0]
    y_values, y_vectors = torch.linalg.eigh(y_axes.T @ y_axes)
    rolled = y_values[1] >= 0.01 * y_values[2] and y_values[0] / y_values.sum() < 0.5 * values[0] / values.sum()
    if not rolled:
        return up if up @ mean_up >= 0 else -up
    up = y_vectors[:, 0]
    looking_down = -(viewmats[:, 2, :3].mean(0) @ up)  # view directions (z axes) point down, against the up
    above = camera_centers(viewmats).mean(0) @ up
    return up if (looking_down if looking_down.abs() > 1e-3 else above) >= 0 else -up


def turntable_viewmats(viewmats: torch.Tensor, frames: int, center: torch.Tensor | None = None) -> torch.Tensor:
    """A turntable of `frames` cameras: camera 0 of `viewmats` orbited about the cameras' mean up axis through
    `center`.

    The up axis is the cameras' common up (`mean_up_axis`). Each camera keeps camera 0's view of `center`, so the
    object stays where camera 0 sees it: the Gaussians of a run trained from noisy poses lie away from the origin (0.4
    units on maryrose from 15 deg / 0.3), and an orbit about the origin swung them across the frame and out of it.

    Args:
        viewmats: [C, 4, 4] world-to-camera matrices (e.g. the training cameras).
        frames: number of views, evenly spaced over 360 degrees.
        center: [3] the point the orbit turns about (e.g. `gaussians.opacity_weighted_center`); None: the origin.

    Returns:
        [frames, 4, 4] world-to-camera matrices; frame 0 is camera 0.
    """
    up = mean_up_axis(viewmats)
    center = torch.zeros_like(up) if center is None else center.to(up)
    angles = torch.arange(frames, dtype=viewmats.dtype, device=viewmats.device) * (2 * math.pi / frames)
    world_turn = so3_exp(angles[:, None] * up)  # [F, 3, 3] turns the world; the camera orbits the other way
    turn = torch.eye(4, dtype=viewmats.dtype, device=viewmats.device).repeat(frames, 1, 1)
    turn[:, :3, :3] = world_turn
    turn[:, :3, 3] = center - world_turn @ center  # x -> R (x - c) + c: the turn about the line through c
    return viewmats[0] @ turn


def azimuth_order(viewmats: torch.Tensor) -> torch.Tensor:
    """[C] camera indices sorted by azimuth about the cameras' mean up axis through the origin."""
    offsets = camera_centers(viewmats)
    up = mean_up_axis(viewmats)
    flat = offsets - (offsets @ up)[:, None] * up
    east = flat[0] / flat[0].norm().clamp_min(1e-12)
    north = torch.linalg.cross(up, east)
    return torch.argsort(torch.atan2(flat @ north, flat @ east))


def interpolated_viewmats(viewmats: torch.Tensor, gaps: torch.Tensor, fractions: torch.Tensor,
                          center: torch.Tensor | None = None) -> torch.Tensor:
    """Cameras part of the way between neighbouring cameras of an orbit around `center`.

    Gap g runs from the g-th to the (g+1)-th camera in `azimuth_order` about `center` (the last gap closes the loop).
    A camera at fraction s of a gap has its centre slerped in direction about `center` with the distance interpolated
    linearly, so it stays on the orbit, and its orientation slerped, ``R_a exp(s log(R_a^T R_b))`` in
    camera-to-world form (cameras more nearly opposite than `OPPOSITE_GAP_DEG`: both turned about the cameras' common
    up, the elevation interpolated), then turned the least so that it sees `center` in the direction its two cameras'
    see it in, interpolated. The Gaussians of a run trained from noisy poses lie away from the origin (0.4 units on
    maryrose from 15 deg / 0.3): cameras slerped about the origin saw them 8-50 px of 128 off where their neighbours
    do.

    Args:
        viewmats: [C, 4, 4] world-to-camera matrices, C >= 2.
        gaps: [K] long gap indices in [0, C).
        fractions: [K] positions along each gap, 0 = its first camera, 1 = its second.
        center: [3] the object centre (e.g. `gaussians.opacity_weighted_center`); None: the origin.

    Returns:
        [K, 4, 4] world-to-camera matrices.
    """
    if center is not None:  # in a world whose origin is `center`: x_cam = R (y + c) + t = R y + (R c + t)
        shift = torch.eye(4, dtype=viewmats.dtype, device=viewmats.device)
        shift[:3, 3] = center.to(viewmats)
        return interpolated_viewmats(viewmats @ shift, gaps, fractions) @ torch.linalg.inv(shift)
    order = azimuth_order(viewmats)
    gaps = gaps.to(viewmats.device)
    first, second = order[gaps], order[(gaps + 1) % len(order)]
    to_world_a, to_world_b = viewmats[first, :3, :3].transpose(1, 2), viewmats[second, :3, :3].transpose(1, 2)
    fractions = fractions.to(viewmats)[:, None]
    rotations = to_world_a @ so3_exp(fractions * so3_log(to_world_a.transpose(1, 2) @ to_world_b))
    offset_a, offset_b = camera_centers(viewmats[first]), camera_centers(viewmats[second])
    distance_a, distance_b = offset_a.norm(dim=-1, keepdim=True), offset_b.norm(dim=-1, keepdim=True)
    direction_a, direction_b = offset_a / distance_a, offset_b / distance_b
    angle = torch.arccos((direction_a * direction_b).sum(-1, keepdim=True).clamp(-1.0, 1.0))
    sin_angle = torch.sin(angle)
    safe = sin_angle > 1e-6  # nearly identical directions: linear interpolation is exact enough
    weight_a = torch.where(safe, torch.sin((1 - fractions) * angle) / sin_angle.clamp_min(1e-6), 1 - fractions)
    weight_b = torch.where(safe, torch.sin(fractions * angle) / sin_angle.clamp_min(1e-6), fractions)
    directions = weight_a * direction_a + weight_b * direction_b
    directions = directions / directions.norm(dim=-1, keepdim=True)
    # Nearly opposite cameras (OPPOSITE_GAP_DEG) have no great circle to follow: exactly opposite, the mixed direction
    # is zero (NaN cameras); a hair above level, the circle ran over the object and a hair below it, under. Those gaps
    # turn about the cameras' common up instead, the way the azimuth order runs, the elevation interpolated, and the
    # orientation with them: turned as the centre is, the rest of the way to the second camera slerped (the half
    # turn between two opposite cameras could turn either way).
    opposite = angle > math.radians(OPPOSITE_GAP_DEG)
    up = mean_up_axis(viewmats)
    height_a, height_b = direction_a @ up, direction_b @ up  # [K] sines of the elevations
    level_a, level_b = direction_a - height_a[:, None] * up, direction_b - height_b[:, None] * up
    sweep = torch.atan2(torch.linalg.cross(level_a, level_b) @ up, (level_a * level_b).sum(-1)) % (2 * math.pi)
    elevation = ((1 - fractions) * torch.atan2(height_a, level_a.norm(dim=-1))[:, None]
                 + fractions * torch.atan2(height_b, level_b.norm(dim=-1))[:, None])
    turns = so3_exp(fractions * sweep[:, None] * up)  # [K, 3, 3] about the up axis
    level = (turns @ level_a[..., None])[..., 0] / level_a.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    directions = torch.where(opposite, torch.cos(elevation) * level + torch.sin(elevation) * up, directions)
    turned_a = so3_exp(sweep[:, None] * up) @ to_world_a
    turned = turns @ to_world_a @ so3_exp(fractions * so3_log(turned_a.transpose(1, 2) @ to_world_b))
    rotations = torch.where(opposite[..., None], turned, rotations)
    centers = directions * ((1 - fractions) * distance_a + fractions * distance_b)
    # The slerped orientation turns about one axis, the centre along the great circle, which rises between cameras
    # on a ring: re-aimed, each camera sees the object centre where its neighbours do (their directions to it,
    # in camera axes, interpolated), or it looked 9 deg off it between 4 views and 60 deg between 2.
    world_to_camera = rotations.transpose(1, 2)
    seen_a = (viewmats[first, :3, :3] @ -offset_a[..., None])[..., 0] / distance_a
    seen_b = (viewmats[second, :3, :3] @ -offset_b[..., None])[..., 0] / distance_b
    wanted = (1 - fractions) * seen_a + fractions * seen_b
    seen = (world_to_camera @ -directions[..., None])[..., 0]
    world_to_camera = rotation_between(seen, wanted / wanted.norm(dim=-1, keepdim=True)) @ world_to_camera
    return viewmats_from_centers(world_to_camera, centers)
