"""Projection: 3D Gaussians -> screen-space means, conics, depths and opacity-aware radii, per camera.

EWA splatting as 3DGS/gsplat: Sigma = R S S^T R^T from the quaternion (w, x, y, z) and linear scales, carried into
camera space by the view rotation, projected with the perspective Jacobian (clamped beside the field of view, as
3DGS does, though wider: see `tangent_limits`, so Gaussians beside the frustum do not explode) and widened by a
low-pass `eps2d` (0.3 px).

The radius is opacity aware: a pixel at Mahalanobis distance d receives alpha = opacity * exp(-d^2/2), which is
below the rasterizer's 1/255 cut-off beyond d^2 = 2 ln(255 opacity). Binning with that radius therefore drops
nothing the rasterizer would have blended (a plain 3-sigma cut changes the image).

Culled Gaussians get radius 0, and a radius of 0 always means culled. The backward kernel is written by hand, as
gsplat's: it recomputes the forward's steps from the inputs and runs their vector-Jacobian products in reverse. It
equals Warp's generated adjoint of the forward kernel (the projection's gradient before it; tests/test_stages.py) up
to float rounding, the clamps included, at about half the cost.
"""

from typing import Any

import warp as wp

from warpbags.kernels.rasterize import ALPHA_THRESHOLD  # the rasterizer skips contributions below this alpha

MAX_RADIUS = wp.constant(2.0**30)  # pixels: a footprint radius that still fits an int32 after the tile arithmetic


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
def tangent_limits(f: Any, c: Any, size: int):
    """(upper, lower) bound of x/z (or y/z) that `perspective_jacobian` clamps to, for one image axis of `size`
    pixels with focal length f and principal point c: the edges widened by 0.3 of the image on both sides, 1.6
    tan(fov / 2) where the principal point is centred. 3DGS clamps at 1.3 tan(fov / 2) (gsplat: the edges widened by
    0.3 tan(fov / 2)); measured with that clamp, the telephoto synthetic scene, whose object fills the frame, ended
    0.54 deg off instead of 0.49 with exact depth maps and 1.85 instead of 1.50 without, the real captures the same
    to the digit (docs/pose-recovery.md, forty-first session)."""
    margin = type(f)(0.3)
    s = type(f)(size)
    return (s - c) / f + margin * s / f, c / f + margin * s / f


@wp.func
def perspective_jacobian(p_cam: Any, fx: Any, fy: Any, cx: Any, cy: Any, width: int, height: int):
    """d(pixel)/d(camera point), with x/z and y/z clamped beside the image's field of view (`tangent_limits`)."""
    lim_x_pos, lim_x_neg = tangent_limits(fx, cx, width)
    lim_y_pos, lim_y_neg = tangent_limits(fy, cy, height)
    z = p_cam[2]
    tx = z * wp.min(lim_x_pos, wp.max(-lim_x_neg, p_cam[0] / z))
    ty = z * wp.min(lim_y_pos, wp.max(-lim_y_neg, p_cam[1] / z))
    zero = type(fx)(0.0)
    return wp.matrix(
        fx / z, zero, -fx * tx / (z * z),
        zero, fy / z, -fy * ty / (z * z),
        shape=(2, 3),
    )


# Warp's generated adjoint is kept (not enable_backward=False): training runs the hand-written backward below, and
# tests/test_stages.py checks that against this adjoint.
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
    # Culling tests are written so that a NaN fails them: a NaN Gaussian is culled on every device (the CPU turned
    # its radius into INT_MIN, which the backward pass then visited, making the camera's gradients NaN).
    if not (depth >= near_plane and depth <= far_plane):
        return
    opacity = opacities[gid]
    if not (opacity >= opacities.dtype(ALPHA_THRESHOLD)):
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
    if not (det > opacities.dtype(0.0)):
        return

    # Largest eigenvalue of the 2D covariance bounds the footprint; scaled by the opacity-aware cut-off.
    mid = opacities.dtype(0.5) * (a + c)
    lambda_max = mid + wp.sqrt(wp.max(opacities.dtype(0.01), mid * mid - det))
    extent_sq = opacities.dtype(2.0) * wp.log(opacity / opacities.dtype(ALPHA_THRESHOLD))
    # Clamped where int32 ends (CUDA saturates the cast, the CPU wrapped a screen-filling Gaussian to INT_MIN).
    radius = wp.min(wp.ceil(wp.sqrt(extent_sq * lambda_max)), opacities.dtype(MAX_RADIUS))
    # Radius 0 (an opacity of exactly 1/255, whose extent is 0) is culled as well: a radius of 0 then always means
    # that nothing was written, and the backward kernel skips those pairs by their radius.
    if not (radius > opacities.dtype(0.0)):
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


# The backward pass, written by hand: Warp's generated adjoint, which replays the forward with its bookkeeping, took
# 3.0 ms per 10k pairs on one core (float32), three times the forward's 1.0; this kernel takes 1.6. Each helper is
# the vector-Jacobian product (VJP) of one forward step: given the gradient of the step's output, those of its
# inputs.


@wp.func
def normalize_vjp(v: Any, v_unit: Any):
    """VJP of v -> v / |v|: the component of v_unit across the unit vector, over |v|; zero at v = 0, where
    wp.normalize returns zero (as Warp's adjoint of it)."""
    length = wp.length(v)
    if length > type(length)(0.0):
        unit = v / length
        return (v_unit - unit * wp.dot(unit, v_unit)) / length
    return v_unit * type(length)(0.0)


@wp.func
def quat_to_rotmat_vjp(quat: Any, v_rot: Any):
    """VJP of `quat_to_rotmat`, through its normalization of the quaternion."""
    q = wp.normalize(quat)
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    two = type(w)(2.0)
    # every entry of R is 2 x a sum of products of two components (1 minus one on the diagonal): d<v_rot, R>/dq is
    # 2 x a linear form in q per component
    v_q = wp.vector(
        x * (v_rot[2, 1] - v_rot[1, 2]) + y * (v_rot[0, 2] - v_rot[2, 0]) + z * (v_rot[1, 0] - v_rot[0, 1]),
        y * (v_rot[0, 1] + v_rot[1, 0]) + z * (v_rot[0, 2] + v_rot[2, 0]) + w * (v_rot[2, 1] - v_rot[1, 2])
        - two * x * (v_rot[1, 1] + v_rot[2, 2]),
        x * (v_rot[0, 1] + v_rot[1, 0]) + z * (v_rot[1, 2] + v_rot[2, 1]) + w * (v_rot[0, 2] - v_rot[2, 0])
        - two * y * (v_rot[0, 0] + v_rot[2, 2]),
        x * (v_rot[0, 2] + v_rot[2, 0]) + y * (v_rot[1, 2] + v_rot[2, 1]) + w * (v_rot[1, 0] - v_rot[0, 1])
        - two * z * (v_rot[0, 0] + v_rot[1, 1]),
    )
    return normalize_vjp(quat, two * v_q)


@wp.func
def covariance_3d_vjp(quat: Any, scale: Any, v_cov: Any):
    """(v_quat, v_scale) of `covariance_3d`, Sigma = M M^T with M = R S: dSigma = dM M^T + M dM^T gives
    v_M = (v_Sigma + v_Sigma^T) M, then v_R = v_M S and v_S the diagonal of R^T v_M."""
    rot = quat_to_rotmat(quat)
    m = rot @ wp.diag(scale)
    v_m = (v_cov + wp.transpose(v_cov)) @ m
    return quat_to_rotmat_vjp(quat, v_m @ wp.diag(scale)), wp.get_diag(wp.transpose(rot) @ v_m)


@wp.func
def congruence_vjp(a: Any, s: Any, v_out: Any):
    """(v_A, v_S) of out = A S A^T for a symmetric S (Sigma carried to the image): with
    d(out) = dA S A^T + A S dA^T + A dS A^T, v_A = (v_out + v_out^T) A S and v_S = A^T v_out A."""
    return (v_out + wp.transpose(v_out)) @ a @ s, wp.transpose(a) @ v_out @ a


@wp.func
def conic_vjp(a: Any, b: Any, c: Any, v_conic: Any):
    """VJP of the conic (c, -b, a) / det, det = a c - b^2, of the 2D covariance [[a, b], [b, c]] (eps2d added): the
    covariance's gradient, with b's at [0, 1] alone, where the forward reads it."""
    det = a * c - b * b
    v_det = -(v_conic[0] * c - v_conic[1] * b + v_conic[2] * a) / (det * det)
    return wp.matrix(
        v_conic[2] / det + v_det * c, -v_conic[1] / det - type(a)(2.0) * v_det * b,
        type(a)(0.0), v_conic[0] / det + v_det * a,
        shape=(2, 2),
    )


@wp.func
def jacobian_row_vjp(p: Any, z: Any, f: Any, c: Any, size: int, v_diagonal: Any, v_last: Any):
    """VJP of one row of `perspective_jacobian`, [f / z on the diagonal, -f t / z^2 last], t = z clamp(p / z), for
    one image axis (p: the camera point's coordinate along it, f, c: its focal length and principal point), given
    the gradients of those two entries: (v_p, v_z, v_f, v_c).

    Where a limit is active, t follows the limit, which depends on f and c, and not p: Warp's adjoints of min and
    max pass the gradient to their first argument where it is strictly the smaller (larger), else to the second.
    """
    upper, lower = tangent_limits(f, c, size)
    ratio = p / z
    above_lower = wp.max(-lower, ratio)
    clamped = wp.min(upper, above_lower)
    t = z * clamped
    z_sq = z * z
    zero = type(z)(0.0)
    v_t = -v_last * f / z_sq
    v_f = v_diagonal / z - v_last * t / z_sq
    v_z = -v_diagonal * f / z_sq + type(z)(2.0) * v_last * f * t / (z_sq * z) + v_t * clamped
    v_clamped = v_t * z
    at_upper = upper < above_lower
    at_lower = -lower > ratio
    v_upper = wp.where(at_upper, v_clamped, zero)
    v_lower = wp.where(at_upper, zero, wp.where(at_lower, -v_clamped, zero))
    v_ratio = wp.where(at_upper, zero, wp.where(at_lower, zero, v_clamped))
    # upper = (size - c) / f + 0.3 size / f and lower = c / f + 0.3 size / f
    v_f += -(v_upper * upper + v_lower * lower) / f
    v_c = (v_lower - v_upper) / f
    return v_ratio / z, v_z - v_ratio * ratio / z, v_f, v_c


@wp.func
def perspective_jacobian_vjp(p_cam: Any, fx: Any, fy: Any, cx: Any, cy: Any, width: int, height: int, v_jac: Any):
    """VJP of `perspective_jacobian`: (v_p_cam, v_intrinsics), the latter as (v_fx, v_fy, v_cx, v_cy)."""
    z = p_cam[2]
    v_px, v_zx, v_fx, v_cx = jacobian_row_vjp(p_cam[0], z, fx, cx, width, v_jac[0, 0], v_jac[0, 2])
    v_py, v_zy, v_fy, v_cy = jacobian_row_vjp(p_cam[1], z, fy, cy, height, v_jac[1, 1], v_jac[1, 2])
    return wp.vector(v_px, v_py, v_zx + v_zy), wp.vector(v_fx, v_fy, v_cx, v_cy)


@wp.func
def pinhole_vjp(p_cam: Any, fx: Any, fy: Any, v_mean2d: Any):
    """VJP of the pixel mean (fx x / z + cx, fy y / z + cy): (v_p_cam, v_intrinsics as (v_fx, v_fy, v_cx, v_cy))."""
    z = p_cam[2]
    v_x = v_mean2d[0] * fx / z
    v_y = v_mean2d[1] * fy / z
    return (
        wp.vector(v_x, v_y, -(v_x * p_cam[0] + v_y * p_cam[1]) / z),
        wp.vector(v_mean2d[0] * p_cam[0] / z, v_mean2d[1] * p_cam[1] / z, v_mean2d[0], v_mean2d[1]),
    )


@wp.func
def viewmat_gradient(v_rot: Any, v_trans: Any):
    """The world-to-camera matrix's gradient from those of its R and t (`view_rotation_translation`)."""
    zero = type(v_trans[0])(0.0)
    return wp.matrix(
        v_rot[0, 0], v_rot[0, 1], v_rot[0, 2], v_trans[0],
        v_rot[1, 0], v_rot[1, 1], v_rot[1, 2], v_trans[1],
        v_rot[2, 0], v_rot[2, 1], v_rot[2, 2], v_trans[2],
        zero, zero, zero, zero,
        shape=(4, 4),
    )


@wp.func
def intrinsics_gradient(v_intrinsics: Any):
    """The pinhole matrix's gradient from that of (fx, fy, cx, cy)."""
    zero = type(v_intrinsics[0])(0.0)
    return wp.matrix(
        v_intrinsics[0], zero, v_intrinsics[2],
        zero, v_intrinsics[1], v_intrinsics[3],
        zero, zero, zero,
        shape=(3, 3),
    )


@wp.kernel(enable_backward=False)
def project_gaussians_backward_kernel(
    means: wp.array(dtype=Any),
    quats: wp.array(dtype=Any),
    scales: wp.array(dtype=Any),
    viewmats: wp.array(dtype=Any),
    Ks: wp.array(dtype=Any),
    width: int,
    height: int,
    eps2d: Any,
    radii: wp.array2d(dtype=wp.int32),
    v_means2d: wp.array2d(dtype=Any),
    v_conics: wp.array2d(dtype=Any),
    v_depths: wp.array2d(dtype=Any),
    v_means: wp.array(dtype=Any),
    v_quats: wp.array(dtype=Any),
    v_scales: wp.array(dtype=Any),
    v_viewmats: wp.array(dtype=Any),
    v_Ks: wp.array(dtype=Any),
):
    """Gradients of `project_gaussians_kernel`'s means2d, conics and depths, accumulated into those of the means,
    quaternions, scales, view matrices and intrinsics: the forward's steps recomputed, then their VJPs in reverse.

    A pair with radius 0 was culled (the forward wrote nothing) and gets no gradient; the opacity only culls, and
    the radius is an integer: neither has one.
    """
    cam, gid = wp.tid()
    if radii[cam, gid] <= 0:
        return
    rot, trans = view_rotation_translation(viewmats[cam])
    mean = means[gid]
    p_cam = rot @ mean + trans
    K = Ks[cam]
    fx = K[0, 0]
    fy = K[1, 1]
    cx = K[0, 2]
    cy = K[1, 2]
    jac = perspective_jacobian(p_cam, fx, fy, cx, cy, width, height)
    quat = quats[gid]
    scale = scales[gid]
    cov3d = covariance_3d(quat, scale)
    # cov2d = (J W) Sigma (J W)^T with W the view rotation: one congruence by the 2 x 3 map from world to pixels,
    # where the forward takes two (W, then J); its backward took 14% less time than one through both.
    to_pixels = jac @ rot
    cov2d = to_pixels @ cov3d @ wp.transpose(to_pixels)

    v_cov2d = conic_vjp(cov2d[0, 0] + eps2d, cov2d[0, 1], cov2d[1, 1] + eps2d, v_conics[cam, gid])
    v_to_pixels, v_cov3d = congruence_vjp(to_pixels, cov3d, v_cov2d)
    v_jac = v_to_pixels @ wp.transpose(rot)
    v_rot = wp.transpose(jac) @ v_to_pixels
    v_quat, v_scale = covariance_3d_vjp(quat, scale, v_cov3d)
    v_p_mean, v_intrinsics_mean = pinhole_vjp(p_cam, fx, fy, v_means2d[cam, gid])
    v_p_jac, v_intrinsics_jac = perspective_jacobian_vjp(p_cam, fx, fy, cx, cy, width, height, v_jac)
    zero = type(eps2d)(0.0)
    v_p_cam = v_p_mean + v_p_jac + wp.vector(zero, zero, v_depths[cam, gid])

    # p_cam = R mean + t
    wp.atomic_add(v_means, gid, wp.transpose(rot) @ v_p_cam)
    wp.atomic_add(v_quats, gid, v_quat)
    wp.atomic_add(v_scales, gid, v_scale)
    wp.atomic_add(v_viewmats, cam, viewmat_gradient(v_rot + wp.outer(v_p_cam, mean), v_p_cam))
    wp.atomic_add(v_Ks, cam, intrinsics_gradient(v_intrinsics_mean + v_intrinsics_jac))
