"""Host-side camera pose math: SO(3)/SE(3) exp and log, pose noise, Sim(3) alignment and pose errors.

Conventions (binding; the renderer uses them):

* ``viewmats`` are world-to-camera ``[C, 4, 4]`` matrices with OpenCV camera axes (x right, y down,
  z forward): ``x_cam = R @ x_world + t`` with ``R = viewmats[..., :3, :3]``, ``t = viewmats[..., :3, 3]``.
* A pose delta is an se(3) 6-vector ordered ``[wx, wy, wz, vx, vy, vz]`` (axis-angle rotation first, then
  translation, as in BARF) and is composed on the LEFT of world-to-camera:
  ``viewmat' = se3_exp(delta) @ viewmat``, i.e. the correction is expressed in the camera frame. It is applied by
  one implementation, the Warp kernel behind `warpbags.wrapper.apply_pose_deltas`; `warpbags.camera_optimizer`
  holds the parameterizations built on it.
* Everything is plain torch, batched over leading dimensions, works in float32 and float64 and on whatever
  device its inputs live on.

Alignment for evaluation maps the estimated camera system into the reference one with a similarity
``x_ref = s R x_est + t`` (see :class:`Sim3`), then compares rotations (geodesic angle, degrees) and camera
centres (Euclidean distance, reference units).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch

__all__ = [
    "Sim3",
    "align_viewmats",
    "azimuth_order",
    "camera_centers",
    "interpolated_viewmats",
    "mean_up_axis",
    "perturb_viewmats",
    "project_points",
    "pose_errors",
    "rotation_error_deg",
    "se3_exp",
    "so3_exp",
    "so3_log",
    "turntable_viewmats",
    "umeyama",
]

# Below this squared angle (rad^2) the exp-map coefficients come from their Taylor series. The series below
# (through theta^12) is exact to float64 rounding up to theta^2 = 0.25, and above it the closed forms lose at
# most ~6 eps / theta^2 relative accuracy (the (theta - sin theta) / theta^3 term), ~1e-6 in float32.
_SERIES_THETA2 = 0.25


def _skew(vectors: torch.Tensor) -> torch.Tensor:
    """Cross-product matrices.

    Args:
        vectors: ``[..., 3]``.

    Returns:
        ``[..., 3, 3]`` matrices ``K`` with ``K @ y == cross(vectors, y)``.
    """
    x, y, z = vectors.unbind(-1)
    zero = torch.zeros_like(x)
    rows = (
        torch.stack([zero, -z, y], dim=-1),
        torch.stack([z, zero, -x], dim=-1),
        torch.stack([-y, x, zero], dim=-1),
    )
    return torch.stack(rows, dim=-2)


def _vee(matrices: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`_skew` applied to the antisymmetric part: ``[..., 3, 3] -> [..., 3]``."""
    antisymmetric = 0.5 * (matrices - matrices.transpose(-1, -2))
    return torch.stack(
        [antisymmetric[..., 2, 1], antisymmetric[..., 0, 2], antisymmetric[..., 1, 0]], dim=-1
    )


def _series(theta2: torch.Tensor, first_factorial: int) -> torch.Tensor:
    """``sum_k (-1)^k theta^(2k) / (first_factorial + 2k)!`` for k = 0..6, by Horner's rule in ``theta2``."""
    result = torch.zeros_like(theta2)
    for k in range(6, -1, -1):
        result = (-1.0) ** k / math.factorial(first_factorial + 2 * k) + theta2 * result
    return result


def _exp_coefficients(omega: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Coefficients of the SO(3)/SE(3) exponential, finite with exact gradients at ``omega = 0``.

    Args:
        omega: ``[..., 3]`` axis-angle vectors, angle ``theta = |omega|``.

    Returns:
        ``(a, b, c)``, each ``[...]``: ``a = sin(theta)/theta``, ``b = (1 - cos(theta))/theta^2``,
        ``c = (theta - sin(theta))/theta^3``.
    """
    theta2 = (omega * omega).sum(dim=-1)
    small = theta2 < _SERIES_THETA2
    # Each branch is evaluated at a harmless stand-in where it is not selected, so that neither the forward
    # values nor the gradients of the unselected branch can be inf/NaN (torch.where would propagate NaN * 0).
    theta = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))
    theta2_series = torch.where(small, theta2, torch.zeros_like(theta2))
    sin_theta = torch.sin(theta)
    half_sinc = torch.sin(0.5 * theta) / (0.5 * theta)
    a = torch.where(small, _series(theta2_series, 1), sin_theta / theta)
    # 1 - cos = 2 sin^2(theta/2) avoids the cancellation of the textbook form.
    b = torch.where(small, _series(theta2_series, 2), 0.5 * half_sinc * half_sinc)
    c = torch.where(small, _series(theta2_series, 3), (theta - sin_theta) / theta**3)
    return a, b, c


def so3_exp(omega: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula: axis-angle vectors to rotation matrices.

    Uses a Taylor series for small angles, so values and autograd gradients are finite and exact at
    ``omega = 0`` (where ``d exp / d omega_k`` is the k-th generator ``skew(e_k)``).

    Args:
        omega: ``[..., 3]`` rotation vectors (unit axis times angle in radians).

    Returns:
        ``[..., 3, 3]`` rotation matrices ``I + a W + b W^2`` with ``W = skew(omega)``.
    """
    a, b, _ = _exp_coefficients(omega)
    skew = _skew(omega)
    identity = torch.eye(3, dtype=omega.dtype, device=omega.device)
    return identity + a[..., None, None] * skew + b[..., None, None] * (skew @ skew)


def so3_log(rotations: torch.Tensor) -> torch.Tensor:
    """Rotation matrices to axis-angle vectors with angle in ``[0, pi]``.

    Robust over the whole range: the angle is ``atan2(|vee(R)|, (tr R - 1)/2)`` (accurate near 0 and pi,
    unlike ``acos``); for angles up to 90 degrees the axis comes from the antisymmetric part (series for
    ``theta / sin(theta)`` near 0), beyond that from the symmetric part ``(R + R^T)/2 - cos(theta) I =
    (1 - cos(theta)) a a^T``, whose sign is fixed by the antisymmetric part. At exactly pi both ``+omega``
    and ``-omega`` are valid; either may be returned. Not meant to be differentiated.

    Args:
        rotations: ``[..., 3, 3]`` rotation matrices.

    Returns:
        ``[..., 3]`` rotation vectors ``omega`` with ``so3_exp(omega) == rotations``.
    """
    sin_axis = _vee(rotations)  # sin(theta) * axis
    sin_theta = torch.linalg.vector_norm(sin_axis, dim=-1)
    trace = rotations.diagonal(dim1=-2, dim2=-1).sum(-1)
    cos_theta = (0.5 * (trace - 1.0)).clamp(-1.0, 1.0)
    theta = torch.atan2(sin_theta, cos_theta)

    # Up to 90 degrees: omega = theta / sin(theta) * vee(R). The ratio has no cancellation; its series
    # 1 + theta^2/6 + 7 theta^4/360 (error < 1e-20 here) only avoids 0/0.
    small = theta * theta < 1e-6
    theta2_series = torch.where(small, theta * theta, torch.zeros_like(theta))
    safe_sin = torch.where(small, torch.ones_like(sin_theta), sin_theta)
    ratio = torch.where(small, 1.0 + theta2_series / 6.0 + 7.0 * theta2_series**2 / 360.0, theta / safe_sin)
    omega_antisymmetric = ratio[..., None] * sin_axis

    # Beyond 90 degrees: axis from the symmetric part, column with the largest diagonal entry.
    one_minus_cos = (1.0 - cos_theta).clamp_min(1.0)  # >= 1 wherever this branch is selected
    identity = torch.eye(3, dtype=rotations.dtype, device=rotations.device)
    outer = (0.5 * (rotations + rotations.transpose(-1, -2)) - cos_theta[..., None, None] * identity) / (
        one_minus_cos[..., None, None]
    )
    best = outer.diagonal(dim1=-2, dim2=-1).argmax(dim=-1)
    column = torch.gather(outer, -1, best[..., None, None].expand(*outer.shape[:-1], 1))[..., 0]
    axis = column / torch.linalg.vector_norm(column, dim=-1, keepdim=True).clamp_min(1e-30)
    sign = torch.where((axis * sin_axis).sum(-1) < 0, -1.0, 1.0).to(rotations.dtype)
    omega_symmetric = (sign * theta)[..., None] * axis

    return torch.where((cos_theta < 0.0)[..., None], omega_symmetric, omega_antisymmetric)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """The SE(3) exponential of twists ordered ``[wx, wy, wz, vx, vy, vz]``.

    ``exp([[W, v], [0, 0]]) = [[R, V v], [0, 1]]`` with ``R = so3_exp(w)`` and
    ``V = I + (1 - cos th)/th^2 W + (th - sin th)/th^3 W^2``; the coefficients use a Taylor series near
    ``th = 0``, so values and gradients are finite and exact at ``xi = 0``.

    Args:
        xi: ``[..., 6]`` twists, rotation (axis-angle, radians) first, then translation.

    Returns:
        ``[..., 4, 4]`` rigid transforms.
    """
    omega, v = xi[..., :3], xi[..., 3:]
    a, b, c = _exp_coefficients(omega)
    skew = _skew(omega)
    skew2 = skew @ skew
    identity = torch.eye(3, dtype=xi.dtype, device=xi.device)
    rotation = identity + a[..., None, None] * skew + b[..., None, None] * skew2
    v_matrix = identity + b[..., None, None] * skew + c[..., None, None] * skew2
    translation = (v_matrix @ v[..., None])[..., 0]
    top = torch.cat([rotation, translation[..., None]], dim=-1)
    bottom = torch.zeros(*xi.shape[:-1], 1, 4, dtype=xi.dtype, device=xi.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def camera_centers(viewmats: torch.Tensor) -> torch.Tensor:
    """Camera centres in world coordinates, ``c = -R^T t``.

    Args:
        viewmats: ``[..., C, 4, 4]`` world-to-camera matrices.

    Returns:
        ``[..., C, 3]`` camera centres (the world points that map to the camera origin).
    """
    rotations = viewmats[..., :3, :3]
    translations = viewmats[..., :3, 3]
    return -(rotations.transpose(-1, -2) @ translations[..., None])[..., 0]


def project_points(viewmats: torch.Tensor, Ks: torch.Tensor, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pinhole projection of world points into every camera.

    Args:
        viewmats: [C, 4, 4] world-to-camera. Ks: [C, 3, 3]. points: [P, 3] world.

    Returns:
        (pixels [C, P, 2] in the image's continuous coordinates (pixel centres at +0.5), depths [C, P]). Points at
        or behind depth 1e-6 get finite but meaningless pixels: mask them by depth.
    """
    cam = points[None] @ viewmats[:, :3, :3].transpose(1, 2) + viewmats[:, None, :3, 3]  # [C, P, 3]
    depths = cam[..., 2]
    safe = torch.where(depths > 1e-6, depths, torch.ones_like(depths))
    u = Ks[:, None, 0, 0] * cam[..., 0] / safe + Ks[:, None, 0, 2]
    v = Ks[:, None, 1, 1] * cam[..., 1] / safe + Ks[:, None, 1, 2]
    return torch.stack([u, v], dim=-1), depths


def _viewmats_from(rotations: torch.Tensor, centers: torch.Tensor) -> torch.Tensor:
    """World-to-camera matrices from rotations ``[..., 3, 3]`` (world-to-camera) and centres ``[..., 3]``."""
    translations = -(rotations @ centers[..., None])
    top = torch.cat([rotations, translations], dim=-1)
    bottom = torch.zeros(*rotations.shape[:-2], 1, 4, dtype=rotations.dtype, device=rotations.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def perturb_viewmats(
    viewmats: torch.Tensor,
    rot_std_deg: float,
    trans_std: float,
    seed: int,
    rot_fixed_deg: float | None = None,
) -> torch.Tensor:
    """Noisy copies of world-to-camera poses, reproducibly from ``seed``.

    Per camera ``i`` (world-to-camera rotation ``R_i``, centre ``c_i``):

    * rotation: ``R_i' = R_noise @ R_i`` with ``R_noise = so3_exp(angle * axis)``, i.e. a rotation in the
      camera frame about the camera's own centre. ``axis`` is uniform on the unit sphere; ``angle`` is drawn
      from ``N(0, rot_std_deg^2)`` degrees, or is exactly ``rot_fixed_deg`` (the BAGS report's fixed-15-degree
      experiment). The geodesic error of camera ``i`` is then ``|angle|`` (for ``|angle| <= 180``).
    * centre: ``c_i' = c_i + n_i`` with ``n_i ~ N(0, trans_std^2 I_3)`` in world units; ``t_i' = -R_i' c_i'``.

    Randomness comes from a local CPU ``torch.Generator`` seeded with ``seed`` (the global RNG state is left
    untouched); draws are made in float64 in the fixed order axes ``[C, 3]``, angles ``[C]``, centre offsets
    ``[C, 3]`` (angles are drawn even when ``rot_fixed_deg`` is given, so the centre noise for a seed does not
    depend on it), then cast to the input's dtype and device. The result is therefore the same on every
    device for a given seed and number of cameras.

    Args:
        viewmats: ``[C, 4, 4]`` world-to-camera matrices (rigid).
        rot_std_deg: standard deviation of the rotation angle, degrees, >= 0. Must be 0 when
            ``rot_fixed_deg`` is given.
        trans_std: standard deviation of each camera-centre coordinate, world units, >= 0.
        seed: seed of the local generator.
        rot_fixed_deg: if given, every camera is rotated by exactly this angle (degrees) about a random axis.

    Returns:
        ``[C, 4, 4]`` perturbed world-to-camera matrices, same dtype and device as ``viewmats``.

    Raises:
        ValueError: negative standard deviations, both ``rot_std_deg`` and ``rot_fixed_deg`` given, or
            ``viewmats`` not of shape ``[C, 4, 4]``.
    """
    if viewmats.ndim != 3 or viewmats.shape[-2:] != (4, 4):
        raise ValueError(f"viewmats must have shape [C, 4, 4], got {list(viewmats.shape)}")
    if rot_std_deg < 0 or trans_std < 0:
        raise ValueError(
            f"noise standard deviations must be >= 0, got rot_std_deg={rot_std_deg}, trans_std={trans_std}"
        )
    if rot_fixed_deg is not None and rot_std_deg != 0:
        raise ValueError(
            f"give either rot_std_deg ({rot_std_deg}) or rot_fixed_deg ({rot_fixed_deg}), not both; set rot_std_deg=0"
        )
    num_cameras = viewmats.shape[0]
    generator = torch.Generator(device="cpu").manual_seed(int(seed))
    draw = dict(generator=generator, dtype=torch.float64, device="cpu")
    axes = torch.randn(num_cameras, 3, **draw)
    axes = axes / torch.linalg.vector_norm(axes, dim=-1, keepdim=True)
    angles_deg = torch.randn(num_cameras, **draw) * rot_std_deg
    if rot_fixed_deg is not None:
        angles_deg = torch.full_like(angles_deg, float(rot_fixed_deg))
    center_offsets = torch.randn(num_cameras, 3, **draw) * trans_std

    rotation_noise = so3_exp(axes * torch.deg2rad(angles_deg)[:, None]).to(viewmats)
    rotations = rotation_noise @ viewmats[:, :3, :3]
    centers = camera_centers(viewmats) + center_offsets.to(viewmats)
    return _viewmats_from(rotations, centers)


@dataclass(frozen=True)
class Sim3:
    """A similarity transform ``x -> scale * rotation @ x + translation``.

    Attributes:
        scale: ``[]`` positive scale.
        rotation: ``[3, 3]`` rotation matrix (det +1).
        translation: ``[3]`` translation.
    """

    scale: torch.Tensor
    rotation: torch.Tensor
    translation: torch.Tensor

    @classmethod
    def identity(cls, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Sim3:
        """The identity transform with the given dtype and device."""
        return cls(
            torch.ones((), dtype=dtype, device=device),
            torch.eye(3, dtype=dtype, device=device),
            torch.zeros(3, dtype=dtype, device=device),
        )

    def apply(self, points: torch.Tensor) -> torch.Tensor:
        """Transform points ``[..., 3] -> [..., 3]``: ``scale * rotation @ p + translation``."""
        return self.scale * (points @ self.rotation.transpose(-1, -2)) + self.translation

    def inverse(self) -> Sim3:
        """The inverse similarity, ``x -> R^T (x - t) / s``."""
        rotation_t = self.rotation.transpose(-1, -2)
        return Sim3(1.0 / self.scale, rotation_t, -(rotation_t @ self.translation) / self.scale)


def umeyama(
    src: torch.Tensor, dst: torch.Tensor, with_scale: bool = True
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Least-squares similarity (Umeyama 1991) with ``dst ≈ s R src + t``.

    Minimises ``sum_n |dst_n - (s R src_n + t)|^2`` over rotations ``R`` (det +1, enforced by the
    determinant fix on the SVD), ``t`` and, if ``with_scale``, ``s > 0`` (else ``s = 1``).

    At least 3 points that are not collinear are required: with 2 points (or collinear points) the scale and
    translation would be defined, but the rotation about the line through the points is not, so this raises
    rather than return an arbitrary rotation. For two cameras use the camera orientations as well
    (``pose_errors(..., alignment="pairwise")``).

    Args:
        src: ``[N, 3]`` source points.
        dst: ``[N, 3]`` destination points, same order.
        with_scale: estimate the scale (Sim(3)) or fix it to 1 (SE(3)).

    Returns:
        ``(scale [], rotation [3, 3], translation [3])`` in the dtype and device of ``src``.

    Raises:
        ValueError: mismatched shapes, N < 3, non-finite values, or collinear / coincident ``src`` points.
    """
    if src.ndim != 2 or src.shape[-1] != 3 or src.shape != dst.shape:
        raise ValueError(
            f"umeyama needs src and dst of the same shape [N, 3], got {list(src.shape)} and {list(dst.shape)}"
        )
    num_points = src.shape[0]
    if num_points < 3:
        raise ValueError(
            f"umeyama needs at least 3 non-collinear points, got {num_points}: the rotation about the line "
            "through 2 points is undetermined"
        )
    if not (torch.isfinite(src).all() and torch.isfinite(dst).all()):
        raise ValueError("umeyama got non-finite (NaN or inf) coordinates")
    dst = dst.to(src)
    src_mean = src.mean(dim=0)
    dst_mean = dst.mean(dim=0)
    src_centered = src - src_mean
    dst_centered = dst - dst_mean

    src_singular = torch.linalg.svdvals(src_centered)
    rank_tolerance = src_singular[0] * max(num_points, 3) * torch.finfo(src.dtype).eps
    if src_singular[0] == 0 or src_singular[1] <= rank_tolerance:
        raise ValueError(
            "umeyama needs source points that are not all collinear (or coincident): the rotation is undetermined"
        )

    covariance = dst_centered.T @ src_centered / num_points  # [3, 3], sum of dst_n src_n^T
    u, singular, vh = torch.linalg.svd(covariance)
    signs = torch.ones(3, dtype=src.dtype, device=src.device)
    if torch.det(u) * torch.det(vh) < 0:
        signs[2] = -1.0
    rotation = u @ torch.diag(signs) @ vh
    if with_scale:
        src_variance = (src_centered * src_centered).sum() / num_points
        scale = (singular * signs).sum() / src_variance
    else:
        scale = torch.ones((), dtype=src.dtype, device=src.device)
    translation = dst_mean - scale * (rotation @ src_mean)
    return scale, rotation, translation


def align_viewmats(viewmats: torch.Tensor, sim3: Sim3) -> torch.Tensor:
    """Map world-to-camera poses through a similarity of the world (estimated frame -> reference frame).

    Camera centres move as points, ``c -> s R c + t``; camera-to-world rotations turn with the world,
    ``R_c2w -> R R_c2w`` (so world-to-camera rotations become ``R_w2c R^T``). The scale changes only the
    translation part.

    Args:
        viewmats: ``[..., C, 4, 4]`` world-to-camera matrices in the source (estimated) frame.
        sim3: the similarity from the source frame to the target (reference) frame.

    Returns:
        ``[..., C, 4, 4]`` world-to-camera matrices in the target frame.
    """
    rotations = viewmats[..., :3, :3] @ sim3.rotation.transpose(-1, -2)
    centers = sim3.apply(camera_centers(viewmats))
    return _viewmats_from(rotations, centers)


def rotation_error_deg(rotations_est: torch.Tensor, rotations_ref: torch.Tensor) -> torch.Tensor:
    """Geodesic angle between rotations, in degrees.

    Computed as ``atan2(|vee(D)|, (tr D - 1)/2)`` with ``D = R_est R_ref^T`` and the cosine clamped to
    ``[-1, 1]``: finite for any input, and, unlike a clamped ``acos``, accurate for tiny angles (``acos``
    cannot resolve angles below ~``sqrt(eps)`` rad, 0.02 degrees in float32). The angle of ``R_est R_ref^T``
    equals that of ``R_est^T R_ref``, so world-to-camera and camera-to-world rotations give the same error.

    Args:
        rotations_est: ``[..., 3, 3]``.
        rotations_ref: ``[..., 3, 3]`` (broadcast against ``rotations_est``).

    Returns:
        ``[...]`` angles in ``[0, 180]`` degrees.
    """
    relative = rotations_est @ rotations_ref.transpose(-1, -2)
    cos_angle = (0.5 * (relative.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0)).clamp(-1.0, 1.0)
    sin_angle = torch.linalg.vector_norm(_vee(relative), dim=-1)
    return torch.rad2deg(torch.atan2(sin_angle, cos_angle))


def _errors_after(
    viewmats_est: torch.Tensor, viewmats_ref: torch.Tensor, sim3: Sim3
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-camera rotation error (degrees) and centre distance after aligning ``viewmats_est`` by ``sim3``."""
    aligned = align_viewmats(viewmats_est, sim3)
    rotation_errors = rotation_error_deg(aligned[..., :3, :3], viewmats_ref[..., :3, :3])
    translation_errors = torch.linalg.vector_norm(
        camera_centers(aligned) - camera_centers(viewmats_ref), dim=-1
    )
    return rotation_errors, translation_errors


def _pairwise_sim3(viewmats_est: torch.Tensor, viewmats_ref: torch.Tensor) -> Sim3:
    """SPARF's small-camera-system alignment (``prealign_w2c_small_camera_systems``); see :func:`pose_errors`."""
    num_cameras = viewmats_est.shape[0]
    if num_cameras < 2:
        raise ValueError(f"pairwise alignment needs at least 2 cameras, got {num_cameras}")
    centers_est = camera_centers(viewmats_est)
    centers_ref = camera_centers(viewmats_ref)
    rotations_est_c2w = viewmats_est[:, :3, :3].transpose(-1, -2)
    rotations_ref_c2w = viewmats_ref[:, :3, :3].transpose(-1, -2)
    distances_est = torch.cdist(centers_est, centers_est)  # [C, C]
    distances_ref = torch.cdist(centers_ref, centers_ref)

    best_key: tuple[float, float, float] | None = None
    best_sim3 = None
    for anchor in range(num_cameras):
        # Rotation and translation make camera `anchor` coincide with its reference (for every scale).
        rotation = rotations_ref_c2w[anchor] @ rotations_est_c2w[anchor].transpose(-1, -2)
        partners = [j for j in range(num_cameras) if j != anchor and distances_est[anchor, j] > 0]
        if not partners:
            continue
        partner_index = torch.tensor(partners, device=viewmats_est.device)
        scales = distances_ref[anchor, partner_index] / distances_est[anchor, partner_index]  # [P]
        # Aligned centres for every partner's scale at once: c' = c_ref[a] + s R (c - c_est[a]).   [P, C, 3]
        offsets = (centers_est - centers_est[anchor]) @ rotation.T
        aligned_centers = centers_ref[anchor] + scales[:, None, None] * offsets
        translation_errors = torch.linalg.vector_norm(aligned_centers - centers_ref, dim=-1)  # [P, C]
        rotation_errors = rotation_error_deg(
            rotation @ rotations_est_c2w, rotations_ref_c2w
        )  # [C], the same for every partner
        mean_rotation = rotation_errors.mean().item()
        for p, mean_translation in enumerate(translation_errors.mean(dim=-1).tolist()):
            key = (mean_rotation * mean_translation, mean_translation, mean_rotation)
            if best_key is None or key < best_key:
                best_key = key
                scale = scales[p]
                best_sim3 = Sim3(scale, rotation, centers_ref[anchor] - scale * (rotation @ centers_est[anchor]))
    if best_sim3 is None:
        raise ValueError("pairwise alignment failed: all estimated camera centres coincide, the scale is undefined")
    return best_sim3


def pose_errors(
    viewmats_est: torch.Tensor,
    viewmats_ref: torch.Tensor,
    alignment: Literal["procrustes", "pairwise", "none"] = "procrustes",
) -> dict:
    """Rotation and translation errors of estimated poses against reference poses, after alignment.

    The estimated poses are first mapped into the reference frame by a Sim(3) (see :func:`align_viewmats`):

    * ``"procrustes"`` (BARF): Umeyama Sim(3) fitted to the camera centres (:func:`umeyama`); needs >= 3
      non-collinear centres. Standard for many views; with 4-9 views it can overfit the noise.
    * ``"pairwise"`` (SPARF's few-view alignment, ``prealign_w2c_small_camera_systems``): for every ordered
      pair ``(i, j)`` of cameras, the Sim(3) whose rotation and translation make camera ``i`` coincide exactly
      with its reference pose and whose scale is ``|c_ref_i - c_ref_j| / |c_est_i - c_est_j|``; the one with
      the lowest ``mean rotation error (deg) * mean translation error`` (SPARF's criterion; exact ties broken
      by mean translation, then mean rotation error) is kept. Needs >= 2 cameras. SPARF only tries the first
      10 cameras; here all pairs are tried (O(C^3) work, meant for few views).
    * ``"none"``: the identity; errors in the raw frames (e.g. to measure injected noise).

    Rotation error is the geodesic angle (:func:`rotation_error_deg`); translation error is the distance
    between aligned and reference camera centres, in reference units (SPARF's definition; BARF's code
    instead takes the norm of the world-to-camera translation difference, which also mixes in rotation
    error). Papers often print the translation error times 100.

    Args:
        viewmats_est: ``[C, 4, 4]`` estimated world-to-camera matrices.
        viewmats_ref: ``[C, 4, 4]`` reference (ground-truth) world-to-camera matrices, same camera order.
        alignment: ``"procrustes"``, ``"pairwise"`` or ``"none"``.

    Returns:
        A dict with ``rotation_errors_deg`` ``[C]`` and ``translation_errors`` ``[C]`` (tensors),
        ``rotation_error_deg_mean``, ``rotation_error_deg_median``, ``translation_error_mean``,
        ``translation_error_median`` (floats), and ``sim3``, the :class:`Sim3` from the estimated to the
        reference frame that was used.

    Raises:
        ValueError: shape mismatch, unknown ``alignment``, or too few / degenerate cameras for the alignment.
    """
    if viewmats_est.ndim != 3 or viewmats_est.shape[-2:] != (4, 4) or viewmats_est.shape != viewmats_ref.shape:
        raise ValueError(
            f"pose_errors needs two [C, 4, 4] tensors of equal shape, got {list(viewmats_est.shape)} "
            f"and {list(viewmats_ref.shape)}"
        )
    viewmats_ref = viewmats_ref.to(viewmats_est)
    with torch.no_grad():
        if alignment == "procrustes":
            try:
                sim3 = Sim3(*umeyama(camera_centers(viewmats_est), camera_centers(viewmats_ref)))
            except ValueError as error:
                raise ValueError(f"procrustes alignment failed: {error}") from error
        elif alignment == "pairwise":
            sim3 = _pairwise_sim3(viewmats_est, viewmats_ref)
        elif alignment == "none":
            sim3 = Sim3.identity(dtype=viewmats_est.dtype, device=viewmats_est.device)
        else:
            raise ValueError(f"alignment must be 'procrustes', 'pairwise' or 'none', got {alignment!r}")
        rotation_errors, translation_errors = _errors_after(viewmats_est, viewmats_ref, sim3)
    return {
        "rotation_errors_deg": rotation_errors,
        "translation_errors": translation_errors,
        "rotation_error_deg_mean": rotation_errors.mean().item(),
        "rotation_error_deg_median": torch.quantile(rotation_errors, 0.5).item(),
        "translation_error_mean": translation_errors.mean().item(),
        "translation_error_median": torch.quantile(translation_errors, 0.5).item(),
        "sim3": sim3,
    }


def mean_up_axis(viewmats: torch.Tensor) -> torch.Tensor:
    """[3] unit world direction of the cameras' mean "up" (-y of OpenCV axes; rows of R are the camera axes)."""
    up = -viewmats[:, 1, :3].mean(0)
    return up / up.norm().clamp_min(1e-12)


def turntable_viewmats(viewmats: torch.Tensor, frames: int, center: torch.Tensor | None = None) -> torch.Tensor:
    """A turntable of `frames` cameras: camera 0 of `viewmats` orbited about the cameras' mean up axis.

    The up axis is the mean of the cameras' "up" directions (-y of OpenCV axes, in world coordinates); the
    rotation is about the line through `center` (default: the origin, the object centre of a normalized scene).

    Args:
        viewmats: [C, 4, 4] world-to-camera matrices (e.g. the training cameras).
        frames: number of views, evenly spaced over 360 degrees.
        center: [3] point the orbit turns about.

    Returns:
        [frames, 4, 4] world-to-camera matrices; frame 0 is camera 0.
    """
    up = mean_up_axis(viewmats)
    center = torch.zeros(3, dtype=viewmats.dtype, device=viewmats.device) if center is None else center
    angles = torch.arange(frames, dtype=viewmats.dtype, device=viewmats.device) * (2 * math.pi / frames)
    world_turn = so3_exp(angles[:, None] * up)  # [F, 3, 3] turns the world; the camera orbits the other way
    to_center = torch.eye(4, dtype=viewmats.dtype, device=viewmats.device).repeat(frames, 1, 1)
    to_center[:, :3, :3] = world_turn
    to_center[:, :3, 3] = center - world_turn @ center
    return viewmats[0] @ to_center



def azimuth_order(viewmats: torch.Tensor, center: torch.Tensor | None = None) -> torch.Tensor:
    """[C] camera indices sorted by azimuth about the cameras' mean up axis through `center` (default: origin)."""
    center = torch.zeros(3, dtype=viewmats.dtype, device=viewmats.device) if center is None else center
    offsets = camera_centers(viewmats) - center
    up = mean_up_axis(viewmats)
    flat = offsets - (offsets @ up)[:, None] * up
    east = flat[0] / flat[0].norm().clamp_min(1e-12)
    north = torch.linalg.cross(up, east)
    return torch.argsort(torch.atan2(flat @ north, flat @ east))


def interpolated_viewmats(viewmats: torch.Tensor, gaps: torch.Tensor, fractions: torch.Tensor,
                          center: torch.Tensor | None = None) -> torch.Tensor:
    """Cameras part of the way between neighbouring cameras of an orbit around `center` (default: the origin).

    Gap g runs from the g-th to the (g+1)-th camera in `azimuth_order` (the last gap closes the loop). A camera at
    fraction s of a gap has its orientation slerped, ``R_a exp(s log(R_a^T R_b))`` in camera-to-world form, and
    its centre slerped in direction about `center` with the distance interpolated linearly, so it stays on the
    orbit.

    Args:
        viewmats: [C, 4, 4] world-to-camera matrices, C >= 2.
        gaps: [K] long gap indices in [0, C).
        fractions: [K] positions along each gap, 0 = its first camera, 1 = its second.
        center: [3] the point the cameras orbit.

    Returns:
        [K, 4, 4] world-to-camera matrices.
    """
    center = torch.zeros(3, dtype=viewmats.dtype, device=viewmats.device) if center is None else center
    order = azimuth_order(viewmats, center)
    gaps = gaps.to(viewmats.device)
    first, second = order[gaps], order[(gaps + 1) % len(order)]
    to_world_a, to_world_b = viewmats[first, :3, :3].transpose(1, 2), viewmats[second, :3, :3].transpose(1, 2)
    fractions = fractions.to(viewmats)[:, None]
    rotations = to_world_a @ so3_exp(fractions * so3_log(to_world_a.transpose(1, 2) @ to_world_b))
    offset_a, offset_b = camera_centers(viewmats[first]) - center, camera_centers(viewmats[second]) - center
    distance_a, distance_b = offset_a.norm(dim=-1, keepdim=True), offset_b.norm(dim=-1, keepdim=True)
    direction_a, direction_b = offset_a / distance_a, offset_b / distance_b
    angle = torch.arccos((direction_a * direction_b).sum(-1, keepdim=True).clamp(-1.0, 1.0))
    sin_angle = torch.sin(angle)
    safe = sin_angle > 1e-6  # nearly identical directions: linear interpolation is exact enough
    weight_a = torch.where(safe, torch.sin((1 - fractions) * angle) / sin_angle.clamp_min(1e-6), 1 - fractions)
    weight_b = torch.where(safe, torch.sin(fractions * angle) / sin_angle.clamp_min(1e-6), fractions)
    directions = weight_a * direction_a + weight_b * direction_b
    directions = directions / directions.norm(dim=-1, keepdim=True)
    centers = center + directions * ((1 - fractions) * distance_a + fractions * distance_b)
    return _viewmats_from(rotations.transpose(1, 2), centers)
