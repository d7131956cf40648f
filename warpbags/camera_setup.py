"""Where a fit's cameras start: the given poses (with the config's noise injected for experiments), the
mask-centroid start, the object centre, the `CameraOptimizer` built on them and its silhouette-coherence solve.

The trainer starts every run here; the repair stage's leave-one-out fits build their (frozen) cameras the same way.
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import torch

from warpbags.camera_optimizer import CameraOptimizer, CameraOptimizerSettings
from warpbags.cameras import camera_centers
from warpbags.configs.train import TrainConfig
from warpbags.correspondences import ViewMatches, epipolar_loss
from warpbags.data.noise import PoseNoise, noisy_viewmats
from warpbags.data.scene import Scene
from warpbags.silhouette import NEARLY_PARALLEL, SilhouetteTargets, centroid_start, rays_meeting_point


def given_viewmats(scene: Scene, config: TrainConfig) -> torch.Tensor:
    """[C,4,4] the poses given to training: the scene's true poses with the config's noise injected (`rot_noise_deg`,
    `rot_noise_fixed`, `trans_noise`, `noise_seed`)."""
    fixed = config.rot_noise_fixed
    noise = PoseNoise(0.0 if fixed else config.rot_noise_deg, config.trans_noise, config.noise_seed,
                      rot_fixed_deg=config.rot_noise_deg if fixed else None)
    viewmats = noisy_viewmats(scene, noise)
    if config.camera.fix_first_camera:
        # The gauge camera defines the world frame (as the first camera in bundle adjustment): it is taken as
        # known, since its delta stays zero and its noise could never be corrected.
        viewmats[0] = scene.viewmats[0]
    return viewmats


def starting_poses(viewmats: torch.Tensor, masks: torch.Tensor | None, Ks: torch.Tensor, config: TrainConfig,
                   log: Callable[[str], None]) -> tuple[torch.Tensor, torch.Tensor]:
    """The poses the optimization starts from ([C,4,4]) and the object centre ([3], world) the cameras agree on.

    With masks, pose optimization and `camera.centroid_start`, each camera is first turned so that its mask-centroid
    ray passes through the rays' meeting point, except a gauge camera (`camera.fix_first_camera`), which keeps its
    given pose. Otherwise the poses stay as given and the centre is where the optical axes (nearly) meet.
    """
    if masks is not None and config.camera.centroid_start and config.pose_opt:
        started = centroid_start(masks.cpu(), viewmats.cpu(), Ks.cpu())
        if started is not None:
            start, center = started[0].to(viewmats), started[1].to(viewmats)
            if config.camera.fix_first_camera:  # the gauge is never corrected, so it must not be turned either
                start[0] = viewmats[0]
            return start, center
        log("the rays through the masks' centroids are nearly parallel (a forward-facing capture?): no "
            "mask-centroid start")
    if masks is None and config.camera.centroid_start and config.pose_opt:
        log("no masks: no mask-centroid start")
    axes = viewmats[:, 2, :3].double().cpu()  # camera z axes in world coordinates
    center = rays_meeting_point(camera_centers(viewmats).double().cpu(), axes, min_spread=NEARLY_PARALLEL)
    if center is None:
        log("the optical axes are nearly parallel (a forward-facing capture?): the object centre is taken at the "
            "world origin, where a scene's normalization puts it")
        center = torch.zeros(3, dtype=torch.float64)
    return viewmats.clone(), center.to(viewmats)


def training_cameras(config: TrainConfig, viewmats: torch.Tensor, object_center: torch.Tensor, Ks: torch.Tensor,
                     width: int, height: int, points: torch.Tensor) -> CameraOptimizer:
    """The camera optimizer of a fit starting at [C,4,4] `viewmats`, as the config sets it (parameterization, gauge,
    learning rates); its preconditioner comes from [P,3] object `points` seen by cameras `Ks` at width x height."""
    settings = CameraOptimizerSettings.from_config(config.camera, lr=config.lr.pose,
                                                   translation_scale=config.lr.pose_translation_scale)
    return CameraOptimizer(viewmats, settings, object_center, Ks, width, height, points)


def coherent_start(cameras: CameraOptimizer, targets: SilhouetteTargets, Ks: torch.Tensor, object_center: torch.Tensor,
                   iterations: int, matches: ViewMatches | None = None, matches_weight: float = 0.0
                   ) -> tuple[float, float]:
    """Solve every camera of `cameras` for silhouette coherence with the others (`SilhouetteTargets.coherence_loss`)
    by L-BFGS, and make that its starting pose (`CameraOptimizer.reset_to`: corrections and moments at zero).

    The mask-centroid start leaves each camera's roll and centre where the noise put them; the masks of the other
    views still constrain them, before any Gaussian is fitted. The solve runs on a float64 copy: the loss falls to
    1e-5 of an image size, and L-BFGS's line search compares such values.

    Args:
        cameras: the fit's camera optimizer (its parameterization, gauge and preconditioner are used).
        targets: the masks' distance transforms (the training views' `silhouettes` where the silhouette terms use
            them). Ks: [C, 3, 3] at the masks' resolution. object_center: [3].
        iterations: L-BFGS iterations.
        matches, matches_weight: feature matches between the views at the masks' resolution, whose epipolar residual
            (`epipolar_loss`) joins the loss with this weight (None or 0: the silhouettes alone).

    Returns:
        (the coherence loss before, after), in image sizes.
    """
    solver = copy.deepcopy(cameras).double()
    Ks, center = Ks.double(), object_center.double()
    radius = targets.object_radius(solver.viewmats(), Ks, center)
    with torch.no_grad():
        before = float(targets.coherence_loss(solver.viewmats(), Ks, center, radius))

    def loss_of(viewmats: torch.Tensor) -> torch.Tensor:
        loss = targets.coherence_loss(viewmats, Ks, center, radius)
        if matches is not None and matches_weight > 0:
            loss = loss + matches_weight * epipolar_loss(viewmats, Ks, matches)
        return loss

    solver.refine(loss_of, iterations)
    solved = solver.viewmats()
    with torch.no_grad():
        after = float(targets.coherence_loss(solved, Ks, center, radius))
    cameras.reset_to(solved)  # the solve started from the cameras' corrected poses: `solved` replaces all of them
    return before, after
