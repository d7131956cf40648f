"""Photometric loss (1 - lambda) L1 + lambda (1 - SSIM) in four separable passes, forward and hand-written backward.

SSIM as 3DGS computes it: per channel, the 11 x 11 Gaussian-window (sigma 1.5) means of x, y, x^2, y^2 and xy with
zero padding, then

    S = (2 mu_x mu_y + c1)(2 s_xy + c2) / ((mu_x^2 + mu_y^2 + c1)(s_x + s_y + c2)),   s_xy = E[xy] - mu_x mu_y, ...

The window is the outer product of a 1-D one and zero padding commutes with it, so each blur is a row pass then
a column pass (22 taps instead of 121). The backward needs S's partials in mu_x, E[x^2] and E[xy] only:

    dS/dE[xy] = 2 A1 / (B1 B2),   dS/dE[x^2] = -S / B2,
    dS/dmu_x = 2 mu_y (A2 - A1) / (B1 B2) - 2 mu_x S (1 / B1 - 1 / B2)

(A1, A2, B1, B2 the four factors above), and since a zero-padded symmetric blur is its own adjoint,
dSSIM/dx = blur(dS/dmu_x) + 2 x blur(dS/dE[x^2]) + y blur(dS/dE[xy]): two more passes.

Images are [B, H, W] arrays of RGB vectors flattened to [B * H * W]; every kernel takes the first pixel of its
launch, so host threads can take disjoint row ranges (a pass finishes before the next starts). Never
differentiated by Warp.
"""

from typing import Any

import warp as wp

WINDOW_RADIUS = 5  # the 11 x 11 window
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


@wp.func
def pixel_row_col(index: int, width: int, height: int):
    """Flat pixel index -> (image, row, column)."""
    per_image = width * height
    image = index / per_image
    local = index - image * per_image
    row = local / width
    return image, row, local - row * width


@wp.func
def signum(v: Any):
    """Componentwise sign with sign(0) = 0 (torch's abs gradient)."""
    zero = type(v[0])(0.0)
    one = type(v[0])(1.0)
    return type(v)(
        wp.where(v[0] > zero, one, wp.where(v[0] < zero, -one, zero)),
        wp.where(v[1] > zero, one, wp.where(v[1] < zero, -one, zero)),
        wp.where(v[2] > zero, one, wp.where(v[2] < zero, -one, zero)),
    )


@wp.kernel(enable_backward=False)
def ssim_row_pass_kernel(
    images: wp.array(dtype=Any),
    targets: wp.array(dtype=Any),
    window: wp.array(dtype=Any),
    width: int,
    height: int,
    first_pixel: int,
    mean_x: wp.array(dtype=Any),
    mean_y: wp.array(dtype=Any),
    mean_xx: wp.array(dtype=Any),
    mean_yy: wp.array(dtype=Any),
    mean_xy: wp.array(dtype=Any),
):
    """The row blur of x, y, x^2, y^2 and xy."""
    pix = first_pixel + wp.tid()
    image, row, col = pixel_row_col(pix, width, height)
    zero = images[pix] * window[0] * type(window[0])(0.0)
    sx = zero
    sy = zero
    sxx = zero
    syy = zero
    sxy = zero
    for tap in range(2 * WINDOW_RADIUS + 1):
        c = col + tap - WINDOW_RADIUS
        if c >= 0 and c < width:
            w = window[tap]
            x = images[pix + c - col]
            y = targets[pix + c - col]
            sx = sx + w * x
            sy = sy + w * y
            sxx = sxx + w * wp.cw_mul(x, x)
            syy = syy + w * wp.cw_mul(y, y)
            sxy = sxy + w * wp.cw_mul(x, y)
    mean_x[pix] = sx
    mean_y[pix] = sy
    mean_xx[pix] = sxx
    mean_yy[pix] = syy
    mean_xy[pix] = sxy


@wp.func
def ssim_terms(mu_x: Any, mu_y: Any, e_xx: Any, e_yy: Any, e_xy: Any):
    """(S, dS/dmu_x, dS/dE[x^2], dS/dE[xy]) of one channel."""
    c1 = type(mu_x)(SSIM_C1)
    c2 = type(mu_x)(SSIM_C2)
    two = type(mu_x)(2.0)
    a1 = two * mu_x * mu_y + c1
    a2 = two * (e_xy - mu_x * mu_y) + c2
    b1 = mu_x * mu_x + mu_y * mu_y + c1
    b2 = (e_xx - mu_x * mu_x) + (e_yy - mu_y * mu_y) + c2
    inv_b = type(mu_x)(1.0) / (b1 * b2)
    s = a1 * a2 * inv_b
    d_mu_x = two * mu_y * (a2 - a1) * inv_b - two * mu_x * s * (type(mu_x)(1.0) / b1 - type(mu_x)(1.0) / b2)
    return s, d_mu_x, -s / b2, two * a1 * inv_b


@wp.kernel(enable_backward=False)
def ssim_column_pass_kernel(
    images: wp.array(dtype=Any),
    targets: wp.array(dtype=Any),
    window: wp.array(dtype=Any),
    width: int,
    height: int,
    first_pixel: int,
    mean_x: wp.array(dtype=Any),
    mean_y: wp.array(dtype=Any),
    mean_xx: wp.array(dtype=Any),
    mean_yy: wp.array(dtype=Any),
    mean_xy: wp.array(dtype=Any),
    ssim_sums: wp.array(dtype=Any),
    l1_sums: wp.array(dtype=Any),
    d_mu_x: wp.array(dtype=Any),
    d_e_xx: wp.array(dtype=Any),
    d_e_xy: wp.array(dtype=Any),
):
    """Column blur of the row-blurred statistics, then per pixel: S and |x - y| summed over the channels, and the
    partials of S for the backward."""
    pix = first_pixel + wp.tid()
    image, row, col = pixel_row_col(pix, width, height)
    zero = images[pix] * window[0] * type(window[0])(0.0)
    mx = zero
    my = zero
    exx = zero
    eyy = zero
    exy = zero
    for tap in range(2 * WINDOW_RADIUS + 1):
        r = row + tap - WINDOW_RADIUS
        if r >= 0 and r < height:
            w = window[tap]
            q = pix + (r - row) * width
            mx = mx + w * mean_x[q]
            my = my + w * mean_y[q]
            exx = exx + w * mean_xx[q]
            eyy = eyy + w * mean_yy[q]
            exy = exy + w * mean_xy[q]
    s0, m0, xx0, xy0 = ssim_terms(mx[0], my[0], exx[0], eyy[0], exy[0])
    s1, m1, xx1, xy1 = ssim_terms(mx[1], my[1], exx[1], eyy[1], exy[1])
    s2, m2, xx2, xy2 = ssim_terms(mx[2], my[2], exx[2], eyy[2], exy[2])
    ssim_sums[pix] = s0 + s1 + s2
    diff = images[pix] - targets[pix]
    l1_sums[pix] = wp.abs(diff[0]) + wp.abs(diff[1]) + wp.abs(diff[2])
    d_mu_x[pix] = type(diff)(m0, m1, m2)
    d_e_xx[pix] = type(diff)(xx0, xx1, xx2)
    d_e_xy[pix] = type(diff)(xy0, xy1, xy2)


@wp.kernel(enable_backward=False)
def ssim_grad_row_pass_kernel(
    window: wp.array(dtype=Any),
    width: int,
    height: int,
    first_pixel: int,
    d_mu_x: wp.array(dtype=Any),
    d_e_xx: wp.array(dtype=Any),
    d_e_xy: wp.array(dtype=Any),
    blurred_mu_x: wp.array(dtype=Any),
    blurred_e_xx: wp.array(dtype=Any),
    blurred_e_xy: wp.array(dtype=Any),
):
    """Row blur of the three partial maps (the adjoint of the column pass's blur)."""
    pix = first_pixel + wp.tid()
    image, row, col = pixel_row_col(pix, width, height)
    zero = d_mu_x[pix] * type(window[0])(0.0)
    a = zero
    b = zero
    c = zero
    for tap in range(2 * WINDOW_RADIUS + 1):
        col_q = col + tap - WINDOW_RADIUS
        if col_q >= 0 and col_q < width:
            w = window[tap]
            q = pix + col_q - col
            a = a + w * d_mu_x[q]
            b = b + w * d_e_xx[q]
            c = c + w * d_e_xy[q]
    blurred_mu_x[pix] = a
    blurred_e_xx[pix] = b
    blurred_e_xy[pix] = c


@wp.kernel(enable_backward=False)
def photometric_grad_kernel(
    images: wp.array(dtype=Any),
    targets: wp.array(dtype=Any),
    window: wp.array(dtype=Any),
    width: int,
    height: int,
    first_pixel: int,
    blurred_mu_x: wp.array(dtype=Any),
    blurred_e_xx: wp.array(dtype=Any),
    blurred_e_xy: wp.array(dtype=Any),
    ssim_scale: Any,
    l1_scale: Any,
    v_images: wp.array(dtype=Any),
):
    """Column blur of the partial maps, combined into d loss / d image: ssim_scale dSSIM_sum/dx + l1_scale sign(x - y)."""
    pix = first_pixel + wp.tid()
    image, row, col = pixel_row_col(pix, width, height)
    zero = images[pix] * type(window[0])(0.0)
    a = zero
    b = zero
    c = zero
    for tap in range(2 * WINDOW_RADIUS + 1):
        r = row + tap - WINDOW_RADIUS
        if r >= 0 and r < height:
            w = window[tap]
            q = pix + (r - row) * width
            a = a + w * blurred_mu_x[q]
            b = b + w * blurred_e_xx[q]
            c = c + w * blurred_e_xy[q]
    x = images[pix]
    y = targets[pix]
    d_ssim = ssim_scale * (a + type(ssim_scale)(2.0) * wp.cw_mul(x, b) + wp.cw_mul(y, c))
    v_images[pix] = d_ssim + l1_scale * signum(x - y)
