"""Projection: 3D Gaussians -> screen-space means, conics, depths and opacity-aware radii, per camera.

EWA splatting as 3DGS/gsplat: Sigma = R S S^T R^T from the quaternion (w, x, y, z) and linear scales, carried into
camera space by the view rotation, projected with the perspective Jacobian (clamped to 1.3x the field of view, as
3DGS does, so Gaussians beside the frustum do not explode) and widened by a low-pass `eps2d` (0.3 px).

The radius is opacity aware: a pixel at Mahalanobis distance d receives alpha = opacity * exp(-d^2/2), which is
below the rasterizer's 1/255 cut-off beyond d^2 = 2 ln(255 opacity). Binning with that radius therefore drops
nothing the rasterizer would have blended (a plain 3-sigma cut changes the image).

No dynamic loops: Warp's automatic adjoint is exact for this kernel. Culled Gaussians get radius 0, and a radius of
0 always means culled.
"""

from typing import Any

import warp as wp

from warpbags.kernels.rasterize import ALPHA_THRESHOLD  # the rasterizer skips contributions below this alpha


@wp.func
def view_rotation_translation(viewmat: Any):
    """(R [3,3], t [3]) of a world-to-camera matrix [R | t]."""
    rot = wp.matrix(
        viewmat[0, 0], viewmat[0, 1], viewmat[0, 2],
        viewmat[1, 0], viewmat[1, 1], viewmat[1, 2],
        viewmat[2, 0], viewmat[2, 1], viewmat[2, 2],
        shape=(3, 3),
    )
    return rot, wp.vector(viewmat[0, 3], viewmat[1, 3], viewmat[2, 3])


@wp.func
def quat_to_rotmat(quat: Any):
    """Rotation matrix of a (w, x, y, z) quaternion, normalized here so any non-zero quaternion is valid."""
    q = wp.normalize(quat)
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    one = type(w)(1.0)
    two = type(w)(2.0)
    return wp.matrix(
        one - two * (y * y + z * z), two * (x * y - w * z), two * (x * z + w * y),
        two * (x * y + w * z), one - two * (x * x + z * z), two * (y * z - w * x),
        two * (x * z - w * y), two * (y * z + w * x), one - two * (x * x + y * y),
        shape=(3, 3),
    )


@wp.func
def covariance_3d(quat: Any, scale: Any):
    """Sigma = (R S)(R S)^T."""
    m = quat_to_rotmat(quat) @ wp.diag(scale)
    return m @ wp.transpose(m)


@wp.func
def perspective_jacobian(p_cam: Any, fx: Any, fy: Any, cx: Any, cy: Any, width: int, height: int):
    """d(pixel)/d(camera point), with x/z and y/z clamped to 1.3x the image's field of view (3DGS)."""
    margin = type(fx)(0.3)
    w = type(fx)(width)
    h = type(fx)(height)
    lim_x_pos = (w - cx) / fx + margin * w / fx
    lim_x_neg = cx / fx + margin * w / fx
    lim_y_pos = (h - cy) / fy + margin * h / fy
    lim_y_neg = cy / fy + margin * h / fy
    z = p_cam[2]
    tx = z * wp.min(lim_x_pos, wp.max(-lim_x_neg, p_cam[0] / z))
    ty = z * wp.min(lim_y_pos, wp.max(-lim_y_neg, p_cam[1] / z))
    zero = type(fx)(0.0)
    return wp.matrix(
        fx / z, zero, -fx * tx / (z * z),
        zero, fy / z, -fy * ty / (z * z),
        shape=(2, 3),
    )


@wp.kernel
def project_gaussians_kernel(
    means: wp.array(dtype=Any),
    quats: wp.array(dtype=Any),
    scales: wp.array(dtype=Any),
    opacities: wp.array(dtype=Any),
    viewmats: wp.array(dtype=Any),
    Ks: wp.array(dtype=Any),
    width: int,
    height: int,
    near_plane: Any,
    far_plane: Any,
    eps2d: Any,
    means2d: wp.array2d(dtype=Any),
    conics: wp.array2d(dtype=Any),
    depths: wp.array2d(dtype=Any),
    radii: wp.array2d(dtype=wp.int32),
):
    cam, gid = wp.tid()
    viewmat = viewmats[cam]
    mean = means[gid]

    rot, trans = view_rotation_translation(viewmat)
    p_cam = rot @ mean + trans
    depth = p_cam[2]
    radii[cam, gid] = 0
    if depth < near_plane or depth > far_plane:
        return
    opacity = opacities[gid]
    if opacity < opacities.dtype(ALPHA_THRESHOLD):
        return

    K = Ks[cam]
    fx = K[0, 0]
    fy = K[1, 1]
    cx = K[0, 2]
    cy = K[1, 2]
    J = perspective_jacobian(p_cam, fx, fy, cx, cy, width, height)
    cov_cam = rot @ covariance_3d(quats[gid], scales[gid]) @ wp.transpose(rot)
    cov2d = J @ cov_cam @ wp.transpose(J)
    a = cov2d[0, 0] + eps2d
    b = cov2d[0, 1]
    c = cov2d[1, 1] + eps2d
    det = a * c - b * b
    if det <= opacities.dtype(0.0):
        return

    # Largest eigenvalue of the 2D covariance bounds the footprint; scaled by the opacity-aware cut-off.
    mid = opacities.dtype(0.5) * (a + c)
    lambda_max = mid + wp.sqrt(wp.max(opacities.dtype(0.01), mid * mid - det))
    extent_sq = opacities.dtype(2.0) * wp.log(opacity / opacities.dtype(ALPHA_THRESHOLD))
    radius = wp.ceil(wp.sqrt(extent_sq * lambda_max))
    # Radius 0 (an opacity of exactly 1/255, whose extent is 0) is culled as well: a radius of 0 then always means
    # that nothing was written.
    if radius <= opacities.dtype(0.0):
        return

    mean2d = wp.vector(fx * p_cam[0] / depth + cx, fy * p_cam[1] / depth + cy)
    if mean2d[0] + radius <= opacities.dtype(0.0) or mean2d[0] - radius >= opacities.dtype(width):
        return
    if mean2d[1] + radius <= opacities.dtype(0.0) or mean2d[1] - radius >= opacities.dtype(height):
        return

    means2d[cam, gid] = mean2d
    conics[cam, gid] = wp.vector(c / det, -b / det, a / det)
    depths[cam, gid] = depth
    radii[cam, gid] = wp.int32(radius)
