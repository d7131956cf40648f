"""Dense plain-torch reference renderer: every pixel against every Gaussian, no tiles, no Warp.

Written independently of kernels/ from the published 3DGS/gsplat equations, so the tiled Warp renderer can be
compared with it forward and backward (autograd through this reference gives the expected gradients). Each stage
has its own reference with the contract of its torch wrapper in warpbags/wrapper.py: `projection_reference`
(`project_gaussians`), `sh_colors_reference` (`spherical_harmonics`), `tiles_reached_reference` and
`tiles_needed_reference` (`bin_gaussians`), `composite_reference` (`rasterize_to_pixels`);
`render_reference` composes them.
"""

from __future__ import annotations

import torch

ALPHA_THRESHOLD = 1 / 255  # 3DGS: a Gaussian contributes to a pixel only where its alpha reaches this

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)


def se3_exp_reference(deltas: torch.Tensor) -> torch.Tensor:
    """[C, 6] (omega, v) -> [C, 4, 4] through the matrix exponential of the twist matrix."""
    w, v = deltas[:, :3], deltas[:, 3:]
    twist = torch.zeros(deltas.shape[0], 4, 4, dtype=deltas.dtype, device=deltas.device)
    twist[:, 0, 1], twist[:, 0, 2], twist[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    twist[:, 1, 0], twist[:, 2, 0], twist[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    twist[:, :3, 3] = v
    return torch.linalg.matrix_exp(twist)


def quat_to_rotmat_reference(quats: torch.Tensor) -> torch.Tensor:
    w, x, y, z = (quats / quats.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(*quats.shape[:-1], 3, 3)


def sh_reference(coeffs: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """coeffs [N, K, 3], unit dirs [N, 3] -> colour [N, 3] = max(SH + 0.5, 0)."""
    x, y, z = dirs.unbind(-1)
    basis = [torch.full_like(x, SH_C0)]
    if degree > 0:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree > 1:
        xx, yy, zz = x * x, y * y, z * z
        basis += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * x * z,
                  SH_C2[4] * (xx - yy)]
    if degree > 2:
        basis += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * x * y * z, SH_C3[2] * y * (4 * zz - xx - yy),
                  SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                  SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    basis = torch.stack(basis, -1)  # [N, B]
    return torch.clamp_min((basis[..., None] * coeffs[:, : basis.shape[-1]]).sum(1) + 0.5, 0.0)


def camera_centers_reference(viewmats: torch.Tensor) -> torch.Tensor:
    """[C, 4, 4] world-to-camera [R | t] -> [C, 3] centres -R^T t (the test oracle's own)."""
    return -torch.einsum("cji,cj->ci", viewmats[:, :3, :3], viewmats[:, :3, 3])


def sh_colors_reference(means: torch.Tensor, coeffs: torch.Tensor, viewmats: torch.Tensor, degree: int) -> torch.Tensor:
    """Colours [C, N, 3] of Gaussians means [N, 3] with SH coeffs [N, K, 3] seen along the ray from each camera
    centre (viewmats [C, 4, 4]): the contract of `warpbags.wrapper.spherical_harmonics`."""
    dirs = means[None] - camera_centers_reference(viewmats)[:, None]  # [C, N, 3]
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    return torch.stack([sh_reference(coeffs, d, degree) for d in dirs])


def ewa_reference(means, quats, scales, viewmat, K, width, height, eps2d=0.3):
    """One camera's EWA splat of every Gaussian: (mean2d [N, 2] pixels, cov2d [N, 2, 2] with the eps2d low-pass,
    camera z [N]). The perspective Jacobian is taken at x/z, y/z clamped to 1.6 tan(fov / 2) (3DGS: 1.3)."""
    rot_g = quat_to_rotmat_reference(quats)
    m = rot_g * scales[:, None, :]
    cov3d = m @ m.transpose(1, 2)
    rot, trans = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ rot.T + trans
    z = p[:, 2]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * width / fx, cx / fx + 0.3 * width / fx
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * height / fy, cy / fy + 0.3 * height / fy
    tx = z * torch.minimum(lim_x_pos, torch.maximum(-lim_x_neg, p[:, 0] / z))
    ty = z * torch.minimum(lim_y_pos, torch.maximum(-lim_y_neg, p[:, 1] / z))
    zeros = torch.zeros_like(z)
    jac = torch.stack([fx / z, zeros, -fx * tx / z**2, zeros, fy / z, -fy * ty / z**2], -1).reshape(-1, 2, 3)
    cov2d = jac @ rot @ cov3d @ rot.T @ jac.transpose(1, 2) + eps2d * torch.eye(2, dtype=means.dtype, device=means.device)
    mean2d = torch.stack([fx * p[:, 0] / z + cx, fy * p[:, 1] / z + cy], -1)
    return mean2d, cov2d, z


def projection_reference(means, quats, scales, opacities, viewmats, Ks, width, height, near_plane=0.01,
                         far_plane=1e10, eps2d=0.3):
    """The contract of `warpbags.wrapper.project_gaussians` (gsplat's projection with an opacity-aware radius).

    Returns:
        means2d [C, N, 2], conics [C, N, 3] (inverse 2D covariance: [0,0], [0,1], [1,1]), depths [C, N], radii
        [C, N] int32 and extents [C, N] (the radius before rounding up). A Gaussian is culled (radius 0, every
        float output 0) when its depth is outside [near_plane, far_plane], its opacity is below 1/255, its 2D
        covariance is not positive definite, its radius is 0 (an opacity of exactly 1/255) or its footprint square
        misses the image. The footprint reaches where alpha = opacity exp(-d^T conic d / 2) >= 1/255, i.e.
        d^T conic d <= 2 ln(255 opacity): along the major axis sqrt(2 ln(255 opacity) lambda_max), with
        lambda_max = mid + sqrt(max(0.01, mid^2 - det)) (gsplat).
    """
    outputs = []
    for viewmat, K in zip(viewmats, Ks):
        mean2d, cov2d, z = ewa_reference(means, quats, scales, viewmat, K, width, height, eps2d)
        a, b, c = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
        det = a * c - b * b
        mid = 0.5 * (a + c)
        lambda_max = mid + torch.sqrt(torch.clamp_min(mid * mid - det, 0.01))
        extent = torch.sqrt(2 * torch.log(opacities / ALPHA_THRESHOLD).clamp_min(0) * lambda_max).detach()
        radius = torch.ceil(extent)
        valid = (z >= near_plane) & (z <= far_plane) & (opacities >= ALPHA_THRESHOLD) & (det > 0) & (radius > 0)
        valid &= (mean2d[:, 0] + radius > 0) & (mean2d[:, 0] - radius < width)
        valid &= (mean2d[:, 1] + radius > 0) & (mean2d[:, 1] - radius < height)
        conic = torch.stack([c / det, -b / det, a / det], -1)
        keep = lambda x: torch.where(valid.reshape(-1, *[1] * (x.dim() - 1)), x, torch.zeros_like(x))  # noqa: E731
        outputs.append((keep(mean2d), keep(conic), keep(z), torch.where(valid, radius, 0).to(torch.int32),
                        torch.where(valid, extent, 0)))
    return tuple(torch.stack(parts) for parts in zip(*outputs))


def project_reference(means, quats, scales, opacities, colors, viewmat, K, width, height, *, sh_degree=None,
                      cam=0, near_plane=0.01, far_plane=1e10, eps2d=0.3):
    """One camera's Gaussians, depth-sorted: (mean2d [N,2], conic a/b/c [N] each, opacity [N], rgb [N,3], z [N],
    valid [N])."""
    mean2d, cov2d, z = ewa_reference(means, quats, scales, viewmat, K, width, height, eps2d)
    a, b, c = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
    det = a * c - b * b
    valid = (z >= near_plane) & (z <= far_plane) & (det > 0) & (opacities >= ALPHA_THRESHOLD)
    if sh_degree is None:
        rgb = colors if colors.dim() == 2 else colors[cam]
    else:
        rgb = sh_colors_reference(means, colors, viewmat[None], sh_degree)[0]
    order = torch.argsort(z.detach())
    return (mean2d[order], (c / det)[order], (-b / det)[order], (a / det)[order], opacities[order], rgb[order],
            z[order], valid[order])


def tile_pixel_boxes(width, height, tile_size, dtype=torch.float64):
    """[tiles_y, tiles_x, 4] (x0, x1, y0, y1): the rectangle of each tile's pixel centres inside the image."""
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    xs = torch.arange(tiles_x, dtype=dtype) * tile_size
    ys = torch.arange(tiles_y, dtype=dtype) * tile_size
    x0, x1 = xs + 0.5, torch.clamp(xs + tile_size, max=width) - 0.5
    y0, y1 = ys + 0.5, torch.clamp(ys + tile_size, max=height) - 0.5
    return torch.stack(torch.broadcast_tensors(x0[None], x1[None], y0[:, None], y1[:, None]), -1)


def tiles_reached_reference(means2d, conics, opacities, radii, width, height, tile_size, slack=0.0):
    """Brute force, tile by tile: does Gaussian n reach tile t of camera c? [C, tiles_y, tiles_x, N] bool.

    Reached: not culled (radius > 0), and the smallest sigma = d^T conic d / 2 over the tile's rectangle of pixel
    centres (inside the image) is at most ln(255 opacity) + slack. The minimum of this convex quadratic over a box
    is 0 when the centre lies in it, else it is on an edge, where it is a clamped 1D minimum.
    """
    boxes = tile_pixel_boxes(width, height, tile_size, means2d.dtype)[None, :, :, None]  # [1, ty, tx, 1, 4]
    mx, my = means2d[:, None, None, :, 0], means2d[:, None, None, :, 1]  # [C, 1, 1, N]
    A, B, C = (conics[:, None, None, :, k] for k in range(3))
    x0, x1, y0, y1 = (boxes[..., k] - (mx if k < 2 else my) for k in range(4))  # box relative to the mean

    def sigma(dx, dy):
        return 0.5 * (A * dx * dx + 2 * B * dx * dy + C * dy * dy)

    inside = (x0 <= 0) & (x1 >= 0) & (y0 <= 0) & (y1 >= 0)
    edges = []
    for dx in (x0, x1):  # vertical edges: best dy for this dx
        edges.append(sigma(dx, torch.minimum(torch.maximum(-B * dx / C, y0), y1)))
    for dy in (y0, y1):  # horizontal edges: best dx for this dy
        edges.append(sigma(torch.minimum(torch.maximum(-B * dy / A, x0), x1), dy))
    least = torch.where(inside, torch.zeros_like(x0), torch.stack(edges).amin(0))
    reach = torch.log(opacities / ALPHA_THRESHOLD)[None, None, None]
    return (least <= reach + slack) & (radii[:, None, None, :] > 0)


def tiles_needed_reference(means2d, conics, opacities, radii, width, height, tile_size):
    """Brute force over pixels: [C, tiles_y, tiles_x, N] bool, True where some pixel centre of the tile gets alpha
    >= 1/255 from a Gaussian that is not culled: the (tile, Gaussian) pairs the rasterizer must see."""
    pixels = pixel_centers(width, height, means2d.dtype)  # [P, 2]
    d = pixels[None, :, None, :] - means2d[:, None]  # [C, P, N, 2]
    A, B, C = (conics[:, None, :, k] for k in range(3))
    sigma = 0.5 * (A * d[..., 0] ** 2 + C * d[..., 1] ** 2) + B * d[..., 0] * d[..., 1]
    hit = (opacities * torch.exp(-sigma) >= ALPHA_THRESHOLD) & (radii[:, None, :] > 0)  # [C, P, N]
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    tile_of_pixel = (pixels[:, 1].long() // tile_size) * tiles_x + pixels[:, 0].long() // tile_size
    counts = torch.zeros(means2d.shape[0], tiles_y * tiles_x, means2d.shape[1], dtype=torch.int64)
    counts.index_add_(1, tile_of_pixel, hit.long())
    return (counts > 0).reshape(means2d.shape[0], tiles_y, tiles_x, -1)


def composite_reference(projected, pixels, early_termination=True):
    """Front-to-back compositing of every Gaussian at every pixel centre [P, 2]: (rgb [P,3], depth [P,1],
    alpha [P,1]), no background. `early_termination=False` composites every Gaussian (to show what stopping
    changes)."""
    mean2d, conic_a, conic_b, conic_c, opacity, rgb, z, valid = projected
    d = pixels[:, None, :] - mean2d[None]  # [P, N, 2]
    sigma = 0.5 * (conic_a * d[..., 0] ** 2 + conic_c * d[..., 1] ** 2) + conic_b * d[..., 0] * d[..., 1]
    alpha = torch.clamp(opacity * torch.exp(-sigma), max=0.99)
    keep = valid & (sigma >= 0) & (alpha >= 1 / 255)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    if early_termination:  # compositing stops before a Gaussian that would bring T to 1e-4 or below
        alpha = torch.where(torch.cumprod(1 - alpha, dim=1) > 1e-4, alpha, torch.zeros_like(alpha))
    t_before = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], 1), dim=1)
    weights = alpha * t_before  # [P, N]
    return weights @ rgb, (weights @ z)[:, None], weights.sum(1, keepdim=True)


def pixel_centers(width, height, dtype=torch.float64, device="cpu"):
    ys, xs = torch.meshgrid(torch.arange(height, dtype=dtype, device=device),
                            torch.arange(width, dtype=dtype, device=device), indexing="ij")
    return torch.stack([xs, ys], -1).reshape(-1, 2) + 0.5


def render_reference(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, sh_degree=None,
                     backgrounds=None, pose_deltas=None, near_plane=0.01, far_plane=1e10, eps2d=0.3,
                     early_termination=True):
    """Same contract as warpbags.rasterization (render_mode "RGB+D"); returns (rgb [C,H,W,3], depth [C,H,W,1],
    alpha [C,H,W,1])."""
    if pose_deltas is not None:
        viewmats = se3_exp_reference(pose_deltas) @ viewmats
    pixels = pixel_centers(width, height, means.dtype, means.device)
    rgbs, depths, alphas = [], [], []
    for cam in range(viewmats.shape[0]):
        projected = project_reference(means, quats, scales, opacities, colors, viewmats[cam], Ks[cam], width, height,
                                      sh_degree=sh_degree, cam=cam, near_plane=near_plane, far_plane=far_plane,
                                      eps2d=eps2d)
        image, depth, alpha = composite_reference(projected, pixels, early_termination)
        if backgrounds is not None:
            image = image + (1 - alpha) * backgrounds[cam]
        rgbs.append(image.reshape(height, width, 3))
        depths.append(depth.reshape(height, width, 1))
        alphas.append(alpha.reshape(height, width, 1))
    return torch.stack(rgbs), torch.stack(depths), torch.stack(alphas)
