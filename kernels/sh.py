"""Spherical-harmonics colour, degrees 0-3, evaluated along the ray from each camera centre to each Gaussian.

The camera centre is -R^T t of the (pose-corrected) world-to-camera matrix, so the view-direction term sends
gradient to the pose as well. Colour = max(SH(dir) + 0.5, 0), the 3DGS convention. No dynamic loops: Warp's
automatic adjoint is exact.
"""

from typing import Any

import warp as wp

from warpbags.kernels.project import view_rotation_translation

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2_0 = 1.0925484305920792
SH_C2_1 = -1.0925484305920792
SH_C2_2 = 0.31539156525252005
SH_C2_3 = -1.0925484305920792
SH_C2_4 = 0.5462742152960396
SH_C3_0 = -0.5900435899266435
SH_C3_1 = 2.890611442640554
SH_C3_2 = -0.4570457994644658
SH_C3_3 = 0.3731763325901154
SH_C3_4 = -0.4570457994644658
SH_C3_5 = 1.445305721320277
SH_C3_6 = -0.5900435899266435


@wp.func
def camera_center(viewmat: Any):
    """-R^T t of a world-to-camera matrix."""
    rot, trans = view_rotation_translation(viewmat)
    return -(wp.transpose(rot) @ trans)


@wp.func
def eval_sh(degree: int, coeffs: Any, gid: int, d: Any):
    """Real SH basis up to `degree` (0-3) dotted with the Gaussian's coefficients [K] (3DGS ordering)."""
    result = type(d[0])(SH_C0) * coeffs[gid, 0]
    if degree > 0:
        x = d[0]
        y = d[1]
        z = d[2]
        result = result - type(d[0])(SH_C1) * y * coeffs[gid, 1] + type(d[0])(SH_C1) * z * coeffs[gid, 2] - type(d[0])(SH_C1) * x * coeffs[gid, 3]
        if degree > 1:
            xx = x * x
            yy = y * y
            zz = z * z
            result = (
                result
                + type(d[0])(SH_C2_0) * x * y * coeffs[gid, 4]
                + type(d[0])(SH_C2_1) * y * z * coeffs[gid, 5]
                + type(d[0])(SH_C2_2) * (type(d[0])(2.0) * zz - xx - yy) * coeffs[gid, 6]
                + type(d[0])(SH_C2_3) * x * z * coeffs[gid, 7]
                + type(d[0])(SH_C2_4) * (xx - yy) * coeffs[gid, 8]
            )
            if degree > 2:
                result = (
                    result
                    + type(d[0])(SH_C3_0) * y * (type(d[0])(3.0) * xx - yy) * coeffs[gid, 9]
                    + type(d[0])(SH_C3_1) * x * y * z * coeffs[gid, 10]
                    + type(d[0])(SH_C3_2) * y * (type(d[0])(4.0) * zz - xx - yy) * coeffs[gid, 11]
                    + type(d[0])(SH_C3_3) * z * (type(d[0])(2.0) * zz - type(d[0])(3.0) * xx - type(d[0])(3.0) * yy) * coeffs[gid, 12]
                    + type(d[0])(SH_C3_4) * x * (type(d[0])(4.0) * zz - xx - yy) * coeffs[gid, 13]
                    + type(d[0])(SH_C3_5) * z * (xx - yy) * coeffs[gid, 14]
                    + type(d[0])(SH_C3_6) * x * (xx - type(d[0])(3.0) * yy) * coeffs[gid, 15]
                )
    return result


@wp.func
def offset_and_clamp(rgb: Any):
    """max(rgb + 0.5, 0): SH coefficients store colour around mid-grey (3DGS)."""
    half = type(rgb[0])(0.5)
    zero = type(rgb[0])(0.0)
    return wp.vector(wp.max(rgb[0] + half, zero), wp.max(rgb[1] + half, zero), wp.max(rgb[2] + half, zero))


@wp.kernel
def sh_to_colors_kernel(
    means: wp.array(dtype=Any),
    coeffs: wp.array2d(dtype=Any),
    viewmats: wp.array(dtype=Any),
    degree: int,
    colors: wp.array2d(dtype=Any),
):
    cam, gid = wp.tid()
    direction = wp.normalize(means[gid] - camera_center(viewmats[cam]))
    rgb = eval_sh(degree, coeffs, gid, direction)
    colors[cam, gid] = offset_and_clamp(rgb)
