"""Lie-group maths of camera poses on the host: SO(3)/SE(3) exponentials, the SO(3) log and the geodesic angle.

Conventions (binding; the renderer and `warpbags.camera_optimizer` use them):

* A pose delta is an se(3) twist ordered ``[wx, wy, wz, vx, vy, vz]`` (axis-angle rotation first, then
  translation, as in BARF), composed on the LEFT of world-to-camera: ``viewmat' = se3_exp(delta) @ viewmat``,
  i.e. the correction is expressed in the camera frame. It is applied by one implementation, the Warp kernel
  behind `warpbags.wrapper.apply_pose_deltas`; `se3_exp` here is the torch reference the tests hold it to, and
  the SO(3) maps serve pose noise, alignment, the mask-centroid start and camera paths.
* Everything is plain torch, batched over leading dimensions, works in float32 and float64 and on whatever
  device its inputs live on.
"""

from __future__ import annotations

import math

import torch

__all__ = ["rotation_between", "rotation_error_deg", "se3_exp", "skew", "so3_exp", "so3_log"]

# Below this squared angle (rad^2) the exp-map coefficients come from their Taylor series. The series below
# (through theta^12) is exact to float64 rounding up to theta^2 = 0.25, and above it the closed forms lose at
# most ~6 eps / theta^2 relative accuracy (the (theta - sin theta) / theta^3 term), ~1e-6 in float32.
_SERIES_THETA2 = 0.25


def skew(vectors: torch.Tensor) -> torch.Tensor:
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
    """Inverse of :func:`skew` applied to the antisymmetric part: ``[..., 3, 3] -> [..., 3]``."""
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
    w = skew(omega)
    identity = torch.eye(3, dtype=omega.dtype, device=omega.device)
    return identity + a[..., None, None] * w + b[..., None, None] * (w @ w)


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

    # Beyond 90 degrees: axis from the symmetric part, column with the largest diagonal entry. Its factor
    # (1 - cos(theta)) > 0 is left in: it changes neither which diagonal entry is largest nor the normalized column.
    identity = torch.eye(3, dtype=rotations.dtype, device=rotations.device)
    outer = 0.5 * (rotations + rotations.transpose(-1, -2)) - cos_theta[..., None, None] * identity
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
    w = skew(omega)
    w2 = w @ w
    identity = torch.eye(3, dtype=xi.dtype, device=xi.device)
    rotation = identity + a[..., None, None] * w + b[..., None, None] * w2
    v_matrix = identity + b[..., None, None] * w + c[..., None, None] * w2
    translation = (v_matrix @ v[..., None])[..., 0]
    top = torch.cat([rotation, translation[..., None]], dim=-1)
    bottom = torch.zeros(*xi.shape[:-1], 1, 4, dtype=xi.dtype, device=xi.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def rotation_between(source: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] the smallest rotations taking unit vectors `source` [..., 3] onto `target` [..., 3]; for opposite
    vectors, whose half turn has no one axis, a half turn about an axis perpendicular to `source`."""
    axis = torch.linalg.cross(source, target)
    sin_angle = axis.norm(dim=-1, keepdim=True)
    cos_angle = (source * target).sum(-1, keepdim=True)
    angle = torch.atan2(sin_angle, cos_angle)
    # opposite (the cross product vanishes, the cosine is -1): any perpendicular axis; the source's cross product with
    # the coordinate axis it is least aligned with is one
    opposite = (sin_angle < 1e-6) & (cos_angle < 0)
    least = torch.nn.functional.one_hot(source.abs().argmin(-1), 3).to(source)
    perpendicular = torch.linalg.cross(source, least)
    axis = torch.where(opposite, perpendicular, axis)
    sin_angle = torch.where(opposite, perpendicular.norm(dim=-1, keepdim=True), sin_angle)
    return so3_exp(axis / sin_angle.clamp_min(1e-12) * angle)


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
