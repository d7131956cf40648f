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

Layout, for vector code. Planes are per channel, in image order, with rows padded to a whole number of runs of
RUN = 8 pixels (arrays of RUN-vectors). A thread computes one run, so each pass's arithmetic is the same for all
lanes and compiles to vector instructions. A column blur reads the run of each of its 11 rows as one vector (a row
outside the image has weight 0). A row blur reads the run and its two neighbours and takes each tap as a shifted
window of them; the planes it reads carry a zero run before and after every row (and zeros past the image's last
column), which is the zero padding. Each pixel sums its taps in the same order as a plain per-pixel loop, and a
pixel past the image's last column is computed but never kept. The column blurs of a kernel's maps share one loop
over the taps (one clamped row and weight per tap for all of them): a helper called per map measured 25-30% slower.

A launch is [runs per row, rows] from the batch's row `first_line` on, so host threads can take disjoint row ranges
(a pass finishes before the next starts). Never differentiated by Warp.
"""

from typing import Any

import warp as wp

WINDOW_RADIUS = 5  # the 11 x 11 window
SSIM_SIGMA = 1.5  # its Gaussian's
TAPS = 2 * WINDOW_RADIUS + 1  # a constant, so that Warp unrolls the loops over the taps
RUN = 8  # pixels per thread, the vector width of every pass
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


@wp.func
def tap_line(line_in_image: int, tap: int, lines: int, window: wp.array(dtype=Any)):
    """The line a tap reads (clamped into the image) and its weight (0 outside the image: zero padding)."""
    other = line_in_image + tap - WINDOW_RADIUS
    weight = wp.where(other >= 0 and other < lines, window[tap], window.dtype(0.0))
    return wp.clamp(other, 0, lines - 1), weight


@wp.func
def filled(value: Any):
    """A run with every lane `value` (typed by the caller: a `float` parameter would make it float32)."""
    return wp.vector(value, length=wp.static(RUN))


@wp.func
def signum(v: Any):
    """Lanewise sign(v) with sign(0) = 0 (torch's abs gradient)."""
    zero = v[0] * type(v[0])(0.0)
    one = zero + type(v[0])(1.0)
    out = v
    for k in range(RUN):
        out[k] = wp.where(v[k] > zero, one, wp.where(v[k] < zero, -one, zero))
    return out


@wp.func
def ssim_terms(mu_x: Any, mu_y: Any, e_xx: Any, e_yy: Any, e_xy: Any):
    """(S, dS/dmu_x, dS/dE[x^2], dS/dE[xy]) of one channel, lanewise over a run."""
    c1 = filled(type(mu_x[0])(SSIM_C1))
    c2 = filled(type(mu_x[0])(SSIM_C2))
    one = filled(type(mu_x[0])(1.0))
    two = type(mu_x[0])(2.0)
    mu_xy = wp.cw_mul(mu_x, mu_y)
    mu_xx = wp.cw_mul(mu_x, mu_x)
    mu_yy = wp.cw_mul(mu_y, mu_y)
    a1 = two * mu_xy + c1
    a2 = two * (e_xy - mu_xy) + c2
    b1 = mu_xx + mu_yy + c1
    b2 = (e_xx - mu_xx) + (e_yy - mu_yy) + c2
    inv_b = wp.cw_div(one, wp.cw_mul(b1, b2))
    s = wp.cw_mul(wp.cw_mul(a1, a2), inv_b)
    d_mu_x = two * wp.cw_mul(wp.cw_mul(mu_y, a2 - a1), inv_b) - two * wp.cw_mul(
        wp.cw_mul(mu_x, s), wp.cw_div(one, b1) - wp.cw_div(one, b2))
    return s, d_mu_x, -wp.cw_div(s, b2), two * wp.cw_mul(a1, inv_b)


@wp.func
def run_with_neighbours(planes: wp.array(dtype=Any), first: int):
    """The runs first, first + 1, first + 2 of a padded row as one vector of 3 RUN values."""
    values = wp.vector(planes[first][0], length=wp.static(3 * RUN))
    for part in range(3):
        run = planes[first + part]
        for k in range(RUN):
            values[part * RUN + k] = run[k]
    return values


@wp.func
def row_tap(values: Any, tap: int):
    """The run's pixels shifted by tap - WINDOW_RADIUS columns, out of `run_with_neighbours`' values."""
    shifted = wp.vector(values[0], length=wp.static(RUN))
    for k in range(RUN):
        shifted[k] = values[k + RUN - WINDOW_RADIUS + tap]
    return shifted


@wp.kernel(enable_backward=False)
def ssim_row_pass_kernel(
    planes: wp.array(dtype=Any),
    window: wp.array(dtype=Any),
    rows: int,
    runs: int,
    first_line: int,
    row_means: wp.array(dtype=Any),
):
    """Row blur of x, y, x^2, y^2 and xy of each channel.

    planes: [6, B * H, runs + 2] padded runs of x's, then y's, channel planes. row_means: [15, B * H, runs] runs,
    statistic 5 c + (x, y, xx, yy, xy) of channel c. rows: B * H.
    """
    run, line = wp.tid()
    line += first_line
    plane = rows * (runs + 2)
    out_plane = rows * runs
    source = line * (runs + 2) + run  # the run before this one, in the padded row
    out = line * runs + run
    zero = window[0] * window.dtype(0.0)
    for ch in range(3):
        xs = run_with_neighbours(planes, ch * plane + source)
        ys = run_with_neighbours(planes, (3 + ch) * plane + source)
        sx = wp.vector(zero, length=wp.static(RUN))
        sy = wp.vector(zero, length=wp.static(RUN))
        sxx = wp.vector(zero, length=wp.static(RUN))
        syy = wp.vector(zero, length=wp.static(RUN))
        sxy = wp.vector(zero, length=wp.static(RUN))
        for tap in range(TAPS):
            w = window[tap]
            x = row_tap(xs, tap)
            y = row_tap(ys, tap)
            sx = sx + w * x
            sy = sy + w * y
            sxx = sxx + w * wp.cw_mul(x, x)
            syy = syy + w * wp.cw_mul(y, y)
            sxy = sxy + w * wp.cw_mul(x, y)
        row_means[5 * ch * out_plane + out] = sx
        row_means[(5 * ch + 1) * out_plane + out] = sy
        row_means[(5 * ch + 2) * out_plane + out] = sxx
        row_means[(5 * ch + 3) * out_plane + out] = syy
        row_means[(5 * ch + 4) * out_plane + out] = sxy


@wp.kernel(enable_backward=False)
def ssim_column_pass_kernel(
    planes: wp.array(dtype=Any),
    window: wp.array(dtype=Any),
    width: int,
    height: int,
    rows: int,
    runs: int,
    first_line: int,
    row_means: wp.array(dtype=Any),
    ssim_sums: wp.array(dtype=Any),
    l1_sums: wp.array(dtype=Any),
    partials: wp.array(dtype=Any),
):
    """Column blur of the row means, then per pixel S and |x - y| summed over the channels and the run's pixels
    (one value per thread), and S's partials for the backward.

    planes: as the row pass's. row_means: [15, B * H, runs] runs (the row pass's output). ssim_sums, l1_sums:
    [B * H * runs]. partials: [9, B * H, runs + 2] padded runs, map 3 c + (dS/dmu_x, dS/dE[x^2], dS/dE[xy]) of
    channel c; 0 past the last column (the caller zeroes the padding runs).
    """
    run, line = wp.tid()
    line += first_line
    image = line / height
    row = line - image * height
    plane = rows * runs
    padded_plane = rows * (runs + 2)
    padded = line * (runs + 2) + run + 1
    zero = window[0] * window.dtype(0.0)
    inside = wp.vector(zero, length=wp.static(RUN))  # 1 on the lanes inside the image
    for k in range(RUN):
        inside[k] = wp.where(run * RUN + k < width, zero + window.dtype(1.0), zero)
    ssim_sum = zero
    l1_sum = zero
    for ch in range(3):
        mx = wp.vector(zero, length=wp.static(RUN))
        my = wp.vector(zero, length=wp.static(RUN))
        exx = wp.vector(zero, length=wp.static(RUN))
        eyy = wp.vector(zero, length=wp.static(RUN))
        exy = wp.vector(zero, length=wp.static(RUN))
        for tap in range(TAPS):
            r, w = tap_line(row, tap, height, window)
            source = 5 * ch * plane + (line - row + r) * runs + run
            mx = mx + w * row_means[source]
            my = my + w * row_means[source + plane]
            exx = exx + w * row_means[source + 2 * plane]
            eyy = eyy + w * row_means[source + 3 * plane]
            exy = exy + w * row_means[source + 4 * plane]
        s, d_mu_x, d_e_xx, d_e_xy = ssim_terms(mx, my, exx, eyy, exy)
        ssim_sum = ssim_sum + wp.dot(s, inside)
        partials[3 * ch * padded_plane + padded] = wp.cw_mul(d_mu_x, inside)
        partials[(3 * ch + 1) * padded_plane + padded] = wp.cw_mul(d_e_xx, inside)
        partials[(3 * ch + 2) * padded_plane + padded] = wp.cw_mul(d_e_xy, inside)
        # past the last column x and y are both 0
        l1_sum = l1_sum + wp.dot(wp.abs(planes[ch * padded_plane + padded] - planes[(3 + ch) * padded_plane + padded]),
                                 filled(window.dtype(1.0)))
    ssim_sums[line * runs + run] = ssim_sum
    l1_sums[line * runs + run] = l1_sum


@wp.kernel(enable_backward=False)
def ssim_grad_row_pass_kernel(
    window: wp.array(dtype=Any),
    rows: int,
    runs: int,
    first_line: int,
    partials: wp.array(dtype=Any),
    blurred: wp.array(dtype=Any),
):
    """Row blur of the nine partial maps (the adjoint of the column pass's blur).

    partials: [9, B * H, runs + 2] padded runs (the column pass's output). blurred: [9, B * H, runs] runs.
    """
    run, line = wp.tid()
    line += first_line
    plane = rows * (runs + 2)
    out_plane = rows * runs
    source = line * (runs + 2) + run
    zero = window[0] * window.dtype(0.0)
    for m in range(9):
        values = run_with_neighbours(partials, m * plane + source)
        total = wp.vector(zero, length=wp.static(RUN))
        for tap in range(TAPS):
            total = total + window[tap] * row_tap(values, tap)
        blurred[m * out_plane + line * runs + run] = total


@wp.kernel(enable_backward=False)
def photometric_grad_kernel(
    planes: wp.array(dtype=Any),
    window: wp.array(dtype=Any),
    height: int,
    rows: int,
    runs: int,
    first_line: int,
    blurred: wp.array(dtype=Any),
    ssim_scale: Any,
    l1_scale: Any,
    v_planes: wp.array(dtype=Any),
):
    """Column blur of the row-blurred partial maps, combined into d loss / d image:
    ssim_scale dSSIM_sum/dx + l1_scale sign(x - y).

    planes: as the row pass's. blurred: [9, B * H, runs] runs (the grad row pass's output). v_planes: [3, B * H,
    runs] runs, the gradient's channel planes (lanes past the last column are not kept).
    """
    run, line = wp.tid()
    line += first_line
    image = line / height
    row = line - image * height
    plane = rows * runs
    padded_plane = rows * (runs + 2)
    padded = line * (runs + 2) + run + 1
    zero = window[0] * window.dtype(0.0)
    two = type(ssim_scale)(2.0)
    for ch in range(3):
        # blur(dS/dmu_x), blur(dS/dE[x^2]), blur(dS/dE[xy]) of this channel
        mu = wp.vector(zero, length=wp.static(RUN))
        xx = wp.vector(zero, length=wp.static(RUN))
        xy = wp.vector(zero, length=wp.static(RUN))
        for tap in range(TAPS):
            r, w = tap_line(row, tap, height, window)
            source = 3 * ch * plane + (line - row + r) * runs + run
            mu = mu + w * blurred[source]
            xx = xx + w * blurred[source + plane]
            xy = xy + w * blurred[source + 2 * plane]
        x = planes[ch * padded_plane + padded]
        y = planes[(3 + ch) * padded_plane + padded]
        d_ssim = mu + two * wp.cw_mul(x, xx) + wp.cw_mul(y, xy)
        v_planes[ch * plane + line * runs + run] = ssim_scale * d_ssim + l1_scale * signum(x - y)


def _declare_overloads() -> None:
    """float32 and float64 variants, declared up front so the module builds once with both."""
    for scalar in (wp.float32, wp.float64):
        run = wp.types.vector(RUN, scalar)
        wp.overload(ssim_row_pass_kernel, [wp.array(dtype=run), wp.array(dtype=scalar), int, int, int,
                                           wp.array(dtype=run)])
        wp.overload(ssim_column_pass_kernel, [wp.array(dtype=run), wp.array(dtype=scalar), int, int, int, int, int,
                                              wp.array(dtype=run), wp.array(dtype=scalar), wp.array(dtype=scalar),
                                              wp.array(dtype=run)])
        wp.overload(ssim_grad_row_pass_kernel, [wp.array(dtype=scalar), int, int, int, wp.array(dtype=run),
                                                wp.array(dtype=run)])
        wp.overload(photometric_grad_kernel, [wp.array(dtype=run), wp.array(dtype=scalar), int, int, int, int,
                                              wp.array(dtype=run), scalar, scalar, wp.array(dtype=run)])


_declare_overloads()
