"""Feature matches between training views and the epipolar residual of the poses (SPARF's idea, without its network).

Where views share texture (neighbours 30-60 deg apart on a textured object), SIFT matches tie the cameras to each
other directly: the Sampson distance of a match under the current poses is zero for every match at the true poses,
whatever the Gaussians. `find_view_matches` finds them once, before training, at the resolution the scene was read
at (a 128 px training image holds few features): SIFT inside each view's mask, Lowe's ratio test, and a fundamental
matrix by MAGSAC for every pair. Only pairs whose fit holds many inliers are kept: a fundamental matrix has 7 degrees
of freedom and fits 15-35 of 60-170 wrong matches by chance (`bench/view_matches.py` counts both kinds on the
synthetic scenes and the real captures). Views about 90 deg apart, as four views of an object are, share no
matches, so the term does nothing there. It is off by default (`TrainConfig.lambda_epipolar`,
`CameraConfig.coherence_epipolar`): with 9 views it brings maryrose 2.4 deg closer to its reference poses, but a
third of the telephoto synthetic scene's kept matches are wrong (repeated texture that a poorly conditioned
fundamental matrix accepts) and cost it 0.2 deg (docs/pose-recovery.md).

Pixel coordinates follow the intrinsics' convention (pixel centres at +0.5), so they scale with the image edges.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from warpbags.lie import skew

__all__ = ["ViewMatches", "epipolar_loss", "find_view_matches", "fundamental_matrices", "match_pair",
           "sampson_distances", "sift_detector", "view_features"]

MASK_EROSION_PX = 2  # features at the mask's edge describe the background too
SIFT_FEATURES = 4000
SIFT_CONTRAST = 0.02  # OpenCV's default 0.04 finds too few on low-contrast objects (maryrose's wood)
RATIO = 0.85
RANSAC_PX = 1.5


@dataclass(frozen=True)
class ViewMatches:
    """Matches between pairs of views: match m links pixel `pixels_a[m]` of view `views_a[m]` with `pixels_b[m]` of
    view `views_b[m]`, in images of `size` (`find_view_matches` gives views_a < views_b; `subset` renumbers each view
    and keeps which side it is on).

    Attributes:
        views_a, views_b: [M] long view indices. pixels_a, pixels_b: [M, 2] float64 pixel coordinates (x, y) with
            pixel centres at +0.5. size: (width, height) of the images the coordinates refer to.
    """

    views_a: torch.Tensor
    views_b: torch.Tensor
    pixels_a: torch.Tensor
    pixels_b: torch.Tensor
    size: tuple[int, int]

    def __len__(self) -> int:
        return len(self.views_a)

    @property
    def pairs(self) -> list[tuple[int, int]]:
        """The view pairs that hold matches."""
        return sorted(set(zip(self.views_a.tolist(), self.views_b.tolist())))

    def scaled_to(self, width: int, height: int) -> ViewMatches:
        """The same matches in the images resized to width x height (as the intrinsics scale: with the edges)."""
        factor = torch.tensor([width / self.size[0], height / self.size[1]], dtype=self.pixels_a.dtype)
        return ViewMatches(self.views_a, self.views_b, self.pixels_a * factor, self.pixels_b * factor, (width, height))

    def subset(self, indices: list[int]) -> ViewMatches:
        """The matches among views `indices`, renumbered as their positions there."""
        position = {view: k for k, view in enumerate(indices)}
        keep = torch.tensor([a in position and b in position
                             for a, b in zip(self.views_a.tolist(), self.views_b.tolist())], dtype=torch.bool)

        def renumbered(views: torch.Tensor) -> torch.Tensor:
            return torch.tensor([position[view] for view in views[keep].tolist()], dtype=torch.long)

        return ViewMatches(renumbered(self.views_a), renumbered(self.views_b), self.pixels_a[keep],
                           self.pixels_b[keep], self.size)


def sift_detector(features: int = SIFT_FEATURES):
    """OpenCV's SIFT as the matches use it. It seeds OpenCV's random numbers too: MAGSAC samples at random, and the
    same images should give the same matches every run."""
    cv2.setRNGSeed(0)
    return cv2.SIFT_create(nfeatures=features, contrastThreshold=SIFT_CONTRAST)


def view_features(image: np.ndarray, mask: np.ndarray | None, sift) -> tuple[np.ndarray, np.ndarray | None]:
    """SIFT keypoints [K, 2] (pixel centres at +0.5) and descriptors [K, 128] of an [H, W, 3] image in [0, 1], inside
    its [H, W] mask eroded by `MASK_EROSION_PX` (None: everywhere)."""
    grey = cv2.cvtColor((np.clip(image, 0, 1) * 255).round().astype(np.uint8), cv2.COLOR_RGB2GRAY)
    region = None
    if mask is not None:
        size = 2 * MASK_EROSION_PX + 1
        region = cv2.erode((mask > 0.5).astype(np.uint8) * 255, np.ones((size, size), np.uint8))
    keypoints, descriptors = sift.detectAndCompute(grey, region)
    # OpenCV puts the first pixel's centre at 0, the intrinsics at 0.5
    return np.array([k.pt for k in keypoints], np.float64).reshape(-1, 2) + 0.5, descriptors


def match_pair(features_a, features_b, ratio: float = RATIO, ransac_px: float = RANSAC_PX
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ratio-test matches of two views' `view_features` and which of them MAGSAC's fundamental matrix keeps:
    ([M, 2] pixels in a, [M, 2] in b, [M] bool inliers)."""
    (points_a, descriptors_a), (points_b, descriptors_b) = features_a, features_b
    none = np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, bool)
    if descriptors_a is None or descriptors_b is None or len(descriptors_a) < 2 or len(descriptors_b) < 2:
        return none
    candidates = cv2.BFMatcher(cv2.NORM_L2).knnMatch(descriptors_a, descriptors_b, k=2)
    good = [pair[0] for pair in candidates if len(pair) == 2 and pair[0].distance < ratio * pair[1].distance]
    matched_a = points_a[[m.queryIdx for m in good]].reshape(-1, 2)
    matched_b = points_b[[m.trainIdx for m in good]].reshape(-1, 2)
    if len(good) < 8:  # the 8-point fit MAGSAC refines with
        return matched_a, matched_b, np.zeros(len(good), bool)
    try:
        _, inliers = cv2.findFundamentalMat(matched_a, matched_b, cv2.USAC_MAGSAC, ransac_px, 0.9999, 100_000)
    except cv2.error:  # USAC asserts on degenerate samples (e.g. many matches on one point) instead of failing
        inliers = None
    return matched_a, matched_b, np.zeros(len(good), bool) if inliers is None else inliers.ravel().astype(bool)


def find_view_matches(images: torch.Tensor, masks: torch.Tensor | None, min_inliers: int) -> ViewMatches:
    """The MAGSAC inliers of every pair of views whose fit keeps at least `min_inliers` of them.

    Args:
        images: [C, H, W, 3] in [0, 1]. masks: [C, H, W] or None.
        min_inliers: a pair with fewer inliers is dropped whole (its matches are mostly chance).
    """
    sift = sift_detector()
    features = [view_features(images[i].numpy(), None if masks is None else masks[i].numpy(), sift)
                for i in range(len(images))]
    views_a, views_b, pixels_a, pixels_b = [], [], [], []
    for a, b in itertools.combinations(range(len(images)), 2):
        matched_a, matched_b, inliers = match_pair(features[a], features[b])
        if inliers.sum() < min_inliers:
            continue
        views_a += [a] * int(inliers.sum())
        views_b += [b] * int(inliers.sum())
        pixels_a.append(matched_a[inliers])
        pixels_b.append(matched_b[inliers])

    def stacked(parts: list[np.ndarray]) -> torch.Tensor:
        return torch.from_numpy(np.concatenate(parts)) if parts else torch.zeros(0, 2, dtype=torch.float64)

    return ViewMatches(torch.tensor(views_a, dtype=torch.long), torch.tensor(views_b, dtype=torch.long),
                       stacked(pixels_a), stacked(pixels_b), (images.shape[2], images.shape[1]))


def fundamental_matrices(viewmats_a: torch.Tensor, viewmats_b: torch.Tensor, Ks_a: torch.Tensor, Ks_b: torch.Tensor
                         ) -> torch.Tensor:
    """[..., 3, 3] F with x_b^T F x_a = 0 for the pixels x_a of camera a and x_b of camera b seeing one point
    (world-to-camera [..., 4, 4], intrinsics [..., 3, 3]); differentiable in the poses."""
    rotation = viewmats_b[..., :3, :3] @ viewmats_a[..., :3, :3].transpose(-1, -2)  # camera a -> camera b
    translation = viewmats_b[..., :3, 3] - (rotation @ viewmats_a[..., :3, 3:])[..., 0]
    return torch.linalg.inv(Ks_b).transpose(-1, -2) @ skew(translation) @ rotation @ torch.linalg.inv(Ks_a)


def sampson_distances(F: torch.Tensor, pixels_a: torch.Tensor, pixels_b: torch.Tensor) -> torch.Tensor:
    """[M] Sampson distances (pixels: the first-order distance of the match to the nearest pair of points that F
    relates) of matches [M, 2] a <-> [M, 2] b under [M, 3, 3] (or [3, 3]) F."""
    ones = torch.ones_like(pixels_a[..., :1])
    homogeneous_a, homogeneous_b = torch.cat([pixels_a, ones], -1), torch.cat([pixels_b, ones], -1)
    lines_b = (F @ homogeneous_a[..., None])[..., 0]  # epipolar lines in b
    lines_a = (F.transpose(-1, -2) @ homogeneous_b[..., None])[..., 0]  # epipolar lines in a
    algebraic = (homogeneous_b * lines_b).sum(-1)
    gradient = lines_b[..., 0] ** 2 + lines_b[..., 1] ** 2 + lines_a[..., 0] ** 2 + lines_a[..., 1] ** 2
    return algebraic.abs() / gradient.clamp_min(torch.finfo(F.dtype).tiny).sqrt()


def epipolar_loss(viewmats: torch.Tensor, Ks: torch.Tensor, matches: ViewMatches) -> torch.Tensor:
    """Mean Cauchy loss log(1 + d^2) of the matches' Sampson distances d in pixels (a scale of 1 px) under the poses
    [C, 4, 4] and intrinsics [C, 3, 3] (at `matches.size`). The Cauchy loss counts a wrong match at most
    logarithmically."""
    if len(matches) == 0:
        return viewmats.sum() * 0.0
    a, b = matches.views_a.to(viewmats.device), matches.views_b.to(viewmats.device)
    F = fundamental_matrices(viewmats[a], viewmats[b], Ks[a].to(viewmats), Ks[b].to(viewmats))
    distances = sampson_distances(F, matches.pixels_a.to(viewmats), matches.pixels_b.to(viewmats))
    return torch.log1p(distances ** 2).mean()
