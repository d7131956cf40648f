"""Comparing estimated camera poses with reference ones: Sim(3) alignment (Umeyama, SPARF's pairwise) and errors.

Alignment for evaluation maps the estimated camera system into the reference one with a similarity
``x_ref = s R x_est + t`` (see :class:`Sim3`), then compares rotations (geodesic angle, degrees) and camera
centres (Euclidean distance, reference units). Poses follow `warpbags.cameras`' conventions.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch

from warpbags.cameras import MIN_DEPTH, camera_centers, moved_keeping_target, project_points, viewmats_from_centers
from warpbags.lie import rotation_error_deg

__all__ = ["Sim3", "align_viewmats", "alignment_for", "centre_floor_errors", "pose_errors", "procrustes_unfit",
           "procrustes_weak", "reprojection_errors", "umeyama"]


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
    rank_tolerance = src_singular[0] * num_points * torch.finfo(src.dtype).eps
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
    return viewmats_from_centers(rotations, centers)


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


# Reference centres whose spread across their main line is below this share of their spread along it count as on
# one line: Procrustes' turn about that line is then fitted to the estimate's noise (centres 1e-6 of their extent
# off a line, poses otherwise exact, read 75 deg off), while the cameras' orientations still fix it (pairwise).
# Above it the turn is fitted, but only as well as the estimate's centre errors against that spread allow: five
# cameras over 4 units and 0.05 off their line, with exact orientations and centres 0.02 off per axis (0.5% of the
# orbit radius), read 8 deg (median over noise draws). For such rigs (a slider with a little sag) ask for pairwise
# (`warpbags eval --pairwise`).
COLLINEAR_SPREAD = 1e-3
# Below this share the turn is fitted but weakly enough to be said (`procrustes_weak`): 4 cameras with exact
# orientations and centres 0.5% of the orbit radius off read 5 deg on a 40 deg arc (share 0.105), 1 deg on a 90 deg
# one (0.243); the 4-9 training views of the shipped and bench scenes spread 0.68 or more.
WEAK_SPREAD = 0.25


def _centre_spread(viewmats_ref: torch.Tensor) -> torch.Tensor:
    """[3] singular values of the cameras' centres about their mean, largest first: their spread along their main
    line, across it, and off their main plane."""
    centres = camera_centers(viewmats_ref.double())
    return torch.linalg.svdvals(centres - centres.mean(dim=0))


def procrustes_unfit(viewmats_ref: torch.Tensor) -> str | None:
    """Why Procrustes on the centres of these reference cameras ([C, 4, 4]) cannot fix the alignment, or None: fewer
    than 3 centres, or centres on one line (`COLLINEAR_SPREAD`; a capture along a slider or a dolly track)."""
    if len(viewmats_ref) < 3:
        return f"{len(viewmats_ref)} cameras: Procrustes needs at least 3 camera centres"
    spread = _centre_spread(viewmats_ref)
    if not torch.isfinite(spread).all():
        return None  # pose_errors names the non-finite poses
    if spread[0] == 0 or spread[1] <= COLLINEAR_SPREAD * spread[0]:
        return "the camera centres lie on one line: Procrustes cannot fix the turn about it"
    return None


def procrustes_weak(viewmats_ref: torch.Tensor) -> str | None:
    """Why Procrustes on the centres of these reference cameras ([C, 4, 4]) fixes its turn only weakly, or None:
    centres spread across their main line less than `WEAK_SPREAD` of along it (a capture from one side, on a short
    arc). None too where Procrustes does not apply (`procrustes_unfit`: 2 cameras, a line), as evaluation aligns those
    pairwise (`alignment_for`) and a warning about Procrustes would describe errors nobody reads."""
    if procrustes_unfit(viewmats_ref):
        return None
    spread = _centre_spread(viewmats_ref)
    if not torch.isfinite(spread).all() or spread[0] == 0 or spread[1] >= WEAK_SPREAD * spread[0]:
        return None
    return (f"the camera centres spread {spread[1] / spread[0]:.2f} as far across their main line as along it: "
            "Procrustes' turn about that line follows the centres' errors")


def alignment_for(viewmats_ref: torch.Tensor, preferred: str = "procrustes") -> str:
    """`preferred`, or "pairwise" where Procrustes cannot be fitted to these reference cameras (`procrustes_unfit`)."""
    return "pairwise" if preferred == "procrustes" and procrustes_unfit(viewmats_ref) else preferred


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
    if not (torch.isfinite(viewmats_est).all() and torch.isfinite(viewmats_ref).all()):
        raise ValueError(f"{alignment} alignment failed: non-finite (NaN or inf) poses")
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


def centre_floor_errors(viewmats_est: torch.Tensor, viewmats_ref: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """[C] rotation errors (degrees) that the estimate's camera centres alone force, after Procrustes alignment.

    The reference cameras are moved to the estimate's aligned centres and turned to keep `target` (the object
    centre, reference frame) where they saw it (`cameras.moved_keeping_target`): their orientation is the best
    any estimate with these centres could have, and their errors are what is left once pan, tilt and roll are
    exact. Far from the object a centre error of d along the orbit turns a camera that looks at the object by
    about d / distance, so rotation errors below this floor need better centres, not better orientations.
    """
    aligned = align_viewmats(viewmats_est, pose_errors(viewmats_est, viewmats_ref)["sim3"])
    best = moved_keeping_target(viewmats_ref, camera_centers(aligned), target.to(viewmats_ref))
    return pose_errors(best, viewmats_ref)["rotation_errors_deg"]


def reprojection_errors(viewmats_est: torch.Tensor, viewmats_ref: torch.Tensor, Ks: torch.Tensor, points: torch.Tensor,
                        sim3: Sim3) -> torch.Tensor:
    """[C] RMS distances (pixels) between where each estimated camera, aligned by `sim3`, and its reference camera
    project `points` ([N, 3], reference frame): the image motion of the object that the pose error causes.

    Degrees alone do not say it: a camera 0.5 deg off about its own centre moves a telephoto image by pixels, but 0.5
    deg along the orbit about the object it looks at moves it by the object's parallax only. The RMS is over the
    points in front of both cameras; it is infinite where a point lies in front of one camera and at or behind the
    other (a camera turned away from the object: its image of them is unbounded, not 0), whichever of the two is
    the estimate (`warpbags agree` compares runs in either order), and NaN where neither sees any point.
    Intrinsics [C, 3, 3] set the pixels' size.
    """
    with torch.no_grad():
        Ks = Ks.to(points)
        pixels_est, depth_est = project_points(align_viewmats(viewmats_est, sim3).to(points), Ks, points)
        pixels_ref, depth_ref = project_points(viewmats_ref.to(points), Ks, points)
        in_front_est, in_front_ref = depth_est > MIN_DEPTH, depth_ref > MIN_DEPTH  # where the pixels are valid
        seen = in_front_est & in_front_ref
        squared = torch.where(seen, ((pixels_est - pixels_ref) ** 2).sum(-1), 0.0)
        rms = (squared.sum(-1) / seen.sum(-1)).sqrt()  # NaN where no point is in front of both
        lost = (in_front_est != in_front_ref).any(-1)
        return torch.where(lost, torch.inf, rms)
