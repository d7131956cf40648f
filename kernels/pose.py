"""Pose transforms: world-to-camera matrices composed with a per-camera correction, one kernel per parameterization.

camera (BARF):   viewmat' = exp(delta) @ viewmat,   delta = [wx, wy, wz, vx, vy, vz]
    a twist in the camera frame: the rotation turns the camera about its own centre.

object (CamP's object-centric "FocalPose" deltas, Park et al. 2023):   params = [wx, wy, wz, ux, uy, s]
    c  = the object centre in the camera frame of `viewmat` (depth clamped to MIN_PIVOT_DEPTH)
    c' = (c_x / c_z + u_x, c_y / c_z + u_y, 1) * c_z * e^s
    viewmat' = [R | c' - R c] @ viewmat,   R = exp(w)
    the rotation turns the camera about the object centre (the centre's image stays put), u shifts the object's
    image by u times the focal length in pixels, s scales its distance. A camera rotation about its own centre and
    a sideways shift move a distant object's image almost alike; here they are one parameter (u), and w is left
    with what only parallax and silhouettes can tell.

The rotation part comes first (as BARF orders its se(3) vector); the exponential is the true SE(3) map (translation
V v, not v). No dynamic loops here, so Warp's automatic adjoint is exact; the small-angle branch keeps both the value
and its gradient finite at zero, where every camera starts.

Kernels are generic over float32/float64 (float64 is what the gradient checks run in).
"""

from typing import Any

import warp as wp

# Below this squared angle (theta < 0.2) the Taylor series, kept through theta^8, is exact to float64 precision
# (next term < 3e-15) and avoids the cancellation in (theta - sin theta) that costs float32 1e-2 relative
# gradient error at theta ~ 1e-3: small deltas are exactly where bundle adjustment lives.
SMALL_ANGLE_SQ = 0.04

# An object centre at or behind the camera has no image to shift: its depth is clamped to this (scene units).
MIN_PIVOT_DEPTH = 1e-3


@wp.func
def so3_coefficients(theta_sq: Any):
    """A = sin(t)/t, B = (1-cos t)/t^2, C = (t - sin t)/t^3 of the SO(3)/SE(3) exponentials."""
    one = type(theta_sq)(1.0)
    if theta_sq < type(theta_sq)(SMALL_ANGLE_SQ):
        t2 = theta_sq
        t4 = t2 * t2
        t6 = t4 * t2
        t8 = t4 * t4
        a = one - t2 / type(t2)(6.0) + t4 / type(t2)(120.0) - t6 / type(t2)(5040.0) + t8 / type(t2)(362880.0)
        b = type(t2)(0.5) - t2 / type(t2)(24.0) + t4 / type(t2)(720.0) - t6 / type(t2)(40320.0) + t8 / type(t2)(3628800.0)
        c = one / type(t2)(6.0) - t2 / type(t2)(120.0) + t4 / type(t2)(5040.0) - t6 / type(t2)(362880.0) + t8 / type(t2)(39916800.0)
        return a, b, c
    theta = wp.sqrt(theta_sq)
    s = wp.sin(theta)
    half_sin = wp.sin(type(theta)(0.5) * theta)
    a = s / theta
    b = type(theta)(2.0) * half_sin * half_sin / theta_sq  # 1 - cos t without cancellation
    c = (theta - s) / (theta_sq * theta)
    return a, b, c


@wp.func
def rigid_matrix(rot: Any, trans: Any):
    """The 4x4 matrix [rot | trans; 0 0 0 1]."""
    zero = type(trans[0])(0.0)
    one = type(trans[0])(1.0)
    return wp.matrix(
        rot[0, 0], rot[0, 1], rot[0, 2], trans[0],
        rot[1, 0], rot[1, 1], rot[1, 2], trans[1],
        rot[2, 0], rot[2, 1], rot[2, 2], trans[2],
        zero, zero, zero, one,
        shape=(4, 4),
    )


@wp.func
def se3_exp(omega: Any, v: Any):
    """exp of the twist (omega, v) as a 4x4 rigid transform (Rodrigues for R, V v for t)."""
    a, b, c = so3_coefficients(wp.dot(omega, omega))
    w = wp.skew(omega)
    w2 = w @ w
    eye = wp.identity(n=3, dtype=type(a))
    return rigid_matrix(eye + a * w + b * w2, (eye + b * w + c * w2) @ v)


@wp.func
def so3_exp(omega: Any):
    """Rodrigues' formula: the rotation matrix of an axis-angle vector."""
    a, b, c = so3_coefficients(wp.dot(omega, omega))
    w = wp.skew(omega)
    return wp.identity(n=3, dtype=type(a)) + a * w + b * (w @ w)


@wp.func
def object_centric_delta(omega: Any, shift_x: Any, shift_y: Any, log_depth: Any, pivot: Any):
    """[R | c' - R c]: turn by exp(omega) about `pivot` c (camera frame), then move c to c' (image shift, depth)."""
    depth = wp.max(pivot[2], type(pivot[2])(MIN_PIVOT_DEPTH))
    center = wp.vector(pivot[0], pivot[1], depth)
    new_depth = depth * wp.exp(log_depth)
    moved = wp.vector((pivot[0] / depth + shift_x) * new_depth, (pivot[1] / depth + shift_y) * new_depth, new_depth)
    rot = so3_exp(omega)
    return rigid_matrix(rot, moved - rot @ center)


@wp.kernel
def apply_pose_deltas_kernel(
    viewmats: wp.array(dtype=Any),
    pose_deltas: wp.array2d(dtype=Any),
    out_viewmats: wp.array(dtype=Any),
):
    cam = wp.tid()
    omega = wp.vector(pose_deltas[cam, 0], pose_deltas[cam, 1], pose_deltas[cam, 2])
    v = wp.vector(pose_deltas[cam, 3], pose_deltas[cam, 4], pose_deltas[cam, 5])
    out_viewmats[cam] = se3_exp(omega, v) @ viewmats[cam]


@wp.kernel
def apply_object_deltas_kernel(
    viewmats: wp.array(dtype=Any),
    object_params: wp.array2d(dtype=Any),
    object_centers: wp.array(dtype=Any),
    out_viewmats: wp.array(dtype=Any),
):
    cam = wp.tid()
    viewmat = viewmats[cam]
    center = object_centers[cam]
    in_camera = viewmat @ wp.vector(center[0], center[1], center[2], type(center[0])(1.0))
    pivot = wp.vector(in_camera[0], in_camera[1], in_camera[2])
    omega = wp.vector(object_params[cam, 0], object_params[cam, 1], object_params[cam, 2])
    delta = object_centric_delta(omega, object_params[cam, 3], object_params[cam, 4], object_params[cam, 5], pivot)
    out_viewmats[cam] = delta @ viewmat
