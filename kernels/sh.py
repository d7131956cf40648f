"""Spherical-harmonics colour, degrees 0-3, evaluated along the ray from each camera centre to each Gaussian.

The camera centre is -R^T t of the (pose-corrected) world-to-camera matrix, so the view-direction term sends
gradient to the pose as well. Colour = max(SH(dir) + 0.5, 0), the 3DGS convention.

The basis is evaluated one band (degree) at a time, `sh_band_1` to `sh_band_3`, and each band has its derivative with
respect to the direction beside it (`sh_band_1_jacobian`, ...): the forward kernel uses the values, the hand-written
backward kernel both. The backward (as gsplat's) equals Warp's generated adjoint of the forward kernel (the
colours' gradient before it; tests/test_stages.py) up to float rounding, the clamp included.
"""

from typing import Any

import warp as wp

from warpbags.kernels.project import normalize_vjp, view_rotation_translation, viewmat_gradient

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
def sh_band_1(d: Any):
    """The degree-1 basis at direction d: the weights of coefficients 1-3 (3DGS ordering)."""
    c1 = type(d[0])(SH_C1)
    return wp.vector(-c1 * d[1], c1 * d[2], -c1 * d[0])


@wp.func
def sh_band_1_jacobian(d: Any):
    """d(sh_band_1)/d(d): [3, 3], a row per basis function."""
    c1 = type(d[0])(SH_C1)
    zero = type(d[0])(0.0)
    return wp.matrix(
        zero, -c1, zero,
        zero, zero, c1,
        -c1, zero, zero,
        shape=(3, 3),
    )


@wp.func
def sh_band_2(d: Any):
    """The degree-2 basis at direction d: the weights of coefficients 4-8."""
    x = d[0]
    y = d[1]
    z = d[2]
    xx = x * x
    yy = y * y
    zz = z * z
    return wp.vector(
        type(x)(SH_C2_0) * x * y,
        type(x)(SH_C2_1) * y * z,
        type(x)(SH_C2_2) * (type(x)(2.0) * zz - xx - yy),
        type(x)(SH_C2_3) * x * z,
        type(x)(SH_C2_4) * (xx - yy),
    )


@wp.func
def sh_band_2_jacobian(d: Any):
    """d(sh_band_2)/d(d): [5, 3], a row per basis function."""
    x = d[0]
    y = d[1]
    z = d[2]
    zero = type(x)(0.0)
    two = type(x)(2.0)
    c2 = type(x)(SH_C2_2)
    return wp.matrix(
        type(x)(SH_C2_0) * y, type(x)(SH_C2_0) * x, zero,
        zero, type(x)(SH_C2_1) * z, type(x)(SH_C2_1) * y,
        -two * c2 * x, -two * c2 * y, type(x)(4.0) * c2 * z,
        type(x)(SH_C2_3) * z, zero, type(x)(SH_C2_3) * x,
        two * type(x)(SH_C2_4) * x, -two * type(x)(SH_C2_4) * y, zero,
        shape=(5, 3),
    )


@wp.func
def sh_band_3(d: Any):
    """The degree-3 basis at direction d: the weights of coefficients 9-15."""
    x = d[0]
    y = d[1]
    z = d[2]
    xx = x * x
    yy = y * y
    zz = z * z
    three = type(x)(3.0)
    return wp.vector(
        type(x)(SH_C3_0) * y * (three * xx - yy),
        type(x)(SH_C3_1) * x * y * z,
        type(x)(SH_C3_2) * y * (type(x)(4.0) * zz - xx - yy),
        type(x)(SH_C3_3) * z * (type(x)(2.0) * zz - three * xx - three * yy),
        type(x)(SH_C3_4) * x * (type(x)(4.0) * zz - xx - yy),
        type(x)(SH_C3_5) * z * (xx - yy),
        type(x)(SH_C3_6) * x * (xx - three * yy),
    )


@wp.func
def sh_band_3_jacobian(d: Any):
    """d(sh_band_3)/d(d): [7, 3], a row per basis function."""
    x = d[0]
    y = d[1]
    z = d[2]
    xx = x * x
    yy = y * y
    zz = z * z
    zero = type(x)(0.0)
    two = type(x)(2.0)
    three = type(x)(3.0)
    six = type(x)(6.0)
    eight = type(x)(8.0)
    c0 = type(x)(SH_C3_0)
    c1 = type(x)(SH_C3_1)
    c2 = type(x)(SH_C3_2)
    c3 = type(x)(SH_C3_3)
    c4 = type(x)(SH_C3_4)
    c5 = type(x)(SH_C3_5)
    c6 = type(x)(SH_C3_6)
    return wp.matrix(
        six * c0 * x * y, three * c0 * (xx - yy), zero,
        c1 * y * z, c1 * x * z, c1 * x * y,
        -two * c2 * x * y, c2 * (type(x)(4.0) * zz - xx - three * yy), eight * c2 * y * z,
        -six * c3 * x * z, -six * c3 * y * z, three * c3 * (two * zz - xx - yy),
        c4 * (type(x)(4.0) * zz - three * xx - yy), -two * c4 * x * y, eight * c4 * x * z,
        two * c5 * x * z, -two * c5 * y * z, c5 * (xx - yy),
        three * c6 * (xx - yy), -six * c6 * x * y, zero,
        shape=(7, 3),
    )


@wp.func
def band_color(basis: Any, coeffs: Any, gid: int, first: int):
    """One band's colour: sum_k basis[k] coeffs[gid, first + k] (an unrolled loop)."""
    result = basis[0] * coeffs[gid, first]
    for k in range(1, len(basis)):
        result = result + basis[k] * coeffs[gid, first + k]
    return result


@wp.func
def band_color_vjp(basis: Any, jacobian: Any, coeffs: Any, gid: int, first: int, v_rgb: Any, v_coeffs: Any):
    """VJP of `band_color`: adds basis[k] v_rgb to v_coeffs[gid, first + k] and returns the direction's gradient,
    sum_k <coeffs[gid, first + k], v_rgb> jacobian[k] (the band's `jacobian` at the direction)."""
    wp.atomic_add(v_coeffs, gid, first, basis[0] * v_rgb)
    v_dir = jacobian[0] * wp.dot(coeffs[gid, first], v_rgb)
    for k in range(1, len(basis)):
        wp.atomic_add(v_coeffs, gid, first + k, basis[k] * v_rgb)
        v_dir = v_dir + jacobian[k] * wp.dot(coeffs[gid, first + k], v_rgb)
    return v_dir


@wp.func
def eval_sh(degree: int, coeffs: Any, gid: int, d: Any):
    """Real SH basis up to `degree` (0-3) dotted with the Gaussian's coefficients [K] (3DGS ordering)."""
    result = type(d[0])(SH_C0) * coeffs[gid, 0]
    if degree > 0:
        result = result + band_color(sh_band_1(d), coeffs, gid, 1)
        if degree > 1:
            result = result + band_color(sh_band_2(d), coeffs, gid, 4)
            if degree > 2:
                result = result + band_color(sh_band_3(d), coeffs, gid, 9)
    return result


@wp.func
def eval_sh_vjp(degree: int, coeffs: Any, gid: int, d: Any, v_rgb: Any, v_coeffs: Any):
    """VJP of `eval_sh`: adds the gradients of the active degree's coefficients to v_coeffs[gid] (those above it get
    none) and returns the direction's (zero at degree 0)."""
    zero = type(d[0])(0.0)
    wp.atomic_add(v_coeffs, gid, 0, type(d[0])(SH_C0) * v_rgb)
    v_dir = wp.vector(zero, zero, zero)
    if degree > 0:
        v_dir = band_color_vjp(sh_band_1(d), sh_band_1_jacobian(d), coeffs, gid, 1, v_rgb, v_coeffs)
        if degree > 1:
            v_dir = v_dir + band_color_vjp(sh_band_2(d), sh_band_2_jacobian(d), coeffs, gid, 4, v_rgb, v_coeffs)
            if degree > 2:
                v_dir = v_dir + band_color_vjp(sh_band_3(d), sh_band_3_jacobian(d), coeffs, gid, 9, v_rgb, v_coeffs)
    return v_dir


@wp.func
def offset_and_clamp(rgb: Any):
    """max(rgb + 0.5, 0): SH coefficients store colour around mid-grey (3DGS)."""
    half = type(rgb[0])(0.5)
    zero = type(rgb[0])(0.0)
    return wp.vector(wp.max(rgb[0] + half, zero), wp.max(rgb[1] + half, zero), wp.max(rgb[2] + half, zero))


@wp.func
def offset_and_clamp_vjp(color: Any, v_color: Any):
    """VJP of `offset_and_clamp`, from its output: a channel's gradient passes where its colour is above 0, that is
    where rgb + 0.5 > 0. So does Warp's adjoint of max(a, b): to a only where a > b, at a tie (and for a NaN a) to
    b, here the constant 0."""
    zero = type(color[0])(0.0)
    return wp.vector(
        wp.where(color[0] > zero, v_color[0], zero),
        wp.where(color[1] > zero, v_color[1], zero),
        wp.where(color[2] > zero, v_color[2], zero),
    )


# Warp's generated adjoint is kept (not enable_backward=False): training runs the hand-written backward below, and
# tests/test_stages.py checks that against this adjoint.
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


@wp.kernel(enable_backward=False)
def sh_to_colors_backward_kernel(
    means: wp.array(dtype=Any),
    coeffs: wp.array2d(dtype=Any),
    viewmats: wp.array(dtype=Any),
    degree: int,
    colors: wp.array2d(dtype=Any),
    v_colors: wp.array2d(dtype=Any),
    v_means: wp.array(dtype=Any),
    v_coeffs: wp.array2d(dtype=Any),
    v_viewmats: wp.array(dtype=Any),
):
    """Gradients of `sh_to_colors_kernel`'s colours (`colors`: its output, which tells the clamped channels),
    accumulated into those of the means, the coefficients (the active degree's) and the view matrices: the direction
    recomputed, then the VJPs of the clamp, the basis, the normalization and the camera centre."""
    cam, gid = wp.tid()
    v_rgb = offset_and_clamp_vjp(colors[cam, gid], v_colors[cam, gid])
    rot, trans = view_rotation_translation(viewmats[cam])
    delta = means[gid] - camera_center(viewmats[cam])
    v_dir = eval_sh_vjp(degree, coeffs, gid, wp.normalize(delta), v_rgb, v_coeffs)
    if degree > 0:  # at degree 0 the colour does not depend on the direction
        v_delta = normalize_vjp(delta, v_dir)
        wp.atomic_add(v_means, gid, v_delta)
        # delta = mean + R^T t
        wp.atomic_add(v_viewmats, cam, viewmat_gradient(wp.outer(trans, v_delta), rot @ v_delta))
