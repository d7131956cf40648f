"""`GaussianModel`: the 3D Gaussians of one fit and everything that changes them, and `TrainingViews`, what they are
fitted to.

A model holds the Gaussian parameters, their Adam groups and position-lr schedule, the densification strategy, and
renders and scores itself against the training views: photometric (L1 + D-SSIM), mask, silhouette (mask distance,
chamfer) and depth terms. It knows nothing of files, rounds or iteration counts: each step is told what to do by a
`StepSettings` (`warpbags.schedule`), and the poses come from a `CameraOptimizer`. The trainer makes one model per
round; the repair stage's leave-one-out fits (`warpbags.repair.pairs`) make their own, with no run folder.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass

import torch

from warpbags.blur import gaussian_blur
from warpbags.camera_optimizer import CameraOptimizer
from warpbags.cameras import camera_centers
from warpbags.configs.train import TrainConfig
from warpbags.correspondences import epipolar_loss
from warpbags.data.scene import Scene
from warpbags.errors import WarpbagsError
from warpbags.gaussians import render_gaussians
from warpbags.init import hull_or_random_points, initial_gaussians
from warpbags.losses import depth_loss, mask_loss, photometric_loss
from warpbags.schedule import StepSettings, exponential_lr
from warpbags.silhouette import SilhouetteTargets
from warpbags.strategy import DensifyStrategy
from warpbags.threads import beside_render


class Diverged(WarpbagsError):
    """A loss or a parameter became NaN or infinite (the message says which)."""


def scene_extent(viewmats: torch.Tensor) -> float:
    """1.1 x the largest distance of a camera centre ([C,4,4] world-to-camera) from their mean (3DGS's extent): the
    scale of the position learning rate and of the densification thresholds."""
    centers = camera_centers(viewmats)
    return 1.1 * float((centers - centers.mean(0)).norm(dim=-1).max())


def gaussian_optimizer(params: dict[str, torch.nn.Parameter], config: TrainConfig, extent: float) -> torch.optim.Adam:
    """Adam with one group per Gaussian parameter (named as the parameter), at the config's initial rates."""
    lr = config.lr
    rates = {"means": lr.means_init * extent, "scales": lr.scales, "quats": lr.quats, "opacities": lr.opacities,
             "sh0": lr.sh_dc, "shN": lr.sh_rest}
    groups = [{"params": [param], "lr": rates[name], "name": name} for name, param in params.items()]
    # fused: one pass per parameter (Adam alone over 101k Gaussians with SH degree 2, one thread: 7.4 ms for the
    # foreach form, 3.1 fused; the per-tensor loop that torch picks on the CPU by default, 14.3). It rounds
    # differently from those two, which agree bit for bit.
    return torch.optim.Adam(groups, lr=0.0, eps=lr.adam_eps, fused=True)


@dataclass
class TrainingViews:
    """The training views at one resolution, on the training device.

    Attributes:
        scene: the views (`Scene`) at this resolution.
        images: [C,H,W,3]; masks, depths: [C,H,W] or None; Ks: [C,3,3] at this resolution.
        backgrounds: [C,3] the background colour of every view.
        targets: [C,H,W,3] the images with the object masked onto the background (GaussianObject), or the images.
        silhouettes: mask distance transforms and edges when a silhouette term is weighted, else None.
    """

    scene: Scene
    images: torch.Tensor
    masks: torch.Tensor | None
    depths: torch.Tensor | None
    Ks: torch.Tensor
    backgrounds: torch.Tensor
    targets: torch.Tensor
    silhouettes: SilhouetteTargets | None

    @classmethod
    def of(cls, scene: Scene, config: TrainConfig, device: torch.device) -> TrainingViews:
        to = dict(device=device)
        images = scene.images.to(**to)
        masks = None if scene.masks is None else scene.masks.to(**to)
        targets = scene.on_background(config.background_rgb).to(**to)
        silhouettes = None
        if masks is not None and (config.lambda_mask_distance > 0 or config.lambda_chamfer > 0):
            silhouettes = SilhouetteTargets(masks).to(device)
        return cls(scene, images, masks, None if scene.depths is None else scene.depths.to(**to), scene.Ks.to(**to),
                   torch.tensor(config.background_rgb, **to).expand(scene.num_views, 3).contiguous(), targets,
                   silhouettes)

    @property
    def num_views(self) -> int:
        return self.scene.num_views

    @property
    def device(self) -> torch.device:
        return self.images.device


class GaussianModel:
    """Gaussians fitted to `training_views`.

    Args:
        config: the training configuration (learning rates, densification, loss weights, render threads).
        training_views: what the loss compares renders with; replaceable (pyramid levels).
        params: name -> Parameter (`warpbags.init.initial_gaussians` names and shapes).
        extent: the scene extent (`scene_extent`).
        generator: the random stream of view sampling and densification (shared with the caller).
    """

    def __init__(self, config: TrainConfig, training_views: TrainingViews, params: dict[str, torch.nn.Parameter],
                 extent: float, generator: torch.Generator):
        self.config, self.training_views, self.generator = config, training_views, generator
        self.params = params
        self.optimizer = gaussian_optimizer(params, config, extent)
        self.strategy = DensifyStrategy(config.densify, extent, white_background=config.background == "white")

    @property
    def scene_extent(self) -> float:
        """The scene extent the position lr and the densification thresholds refer to (held by the strategy)."""
        return self.strategy.scene_extent

    @classmethod
    def initialized(cls, config: TrainConfig, training_views: TrainingViews, viewmats: torch.Tensor, extent: float,
                    generator: torch.Generator, log: Callable[[str], None]) -> GaussianModel:
        """Fresh Gaussians from `config.init` (the visual hull carved with [C,4,4] `viewmats`, SfM or random
        points); says how through `log`."""
        views = training_views
        points, colors, note = hull_or_random_points(
            views.images.cpu(), None if views.masks is None else views.masks.cpu(), viewmats.cpu(), views.Ks.cpu(),
            method=config.init, count=config.init_points, resolution=config.hull_resolution,
            dilation_px=config.hull_dilation_px, missed_views=config.hull_missed_views, generator=generator,
            sfm_points=views.scene.points, sfm_colors=views.scene.point_colors,
        )
        log(f"initialization: {note}")
        raw = initial_gaussians(points, colors, config.sh_degree)
        params = {name: torch.nn.Parameter(value.to(views.device)) for name, value in raw.items()}
        return cls(config, training_views, params, extent, generator)

    @property
    def num_gaussians(self) -> int:
        return len(self.params["means"])

    # ----------------------------------------------------------------------------------------------- render, loss
    def render(self, views: torch.Tensor, viewmats: torch.Tensor, sh_degree: int, depth: bool = True):
        """Render training views `views` ([B] long) from [B,4,4] `viewmats`: (colors+depth [B,H,W,4], or colors
        [B,H,W,3] without `depth`, alphas, meta)."""
        data = self.training_views
        return render_gaussians(self.params, viewmats, data.Ks[views], data.scene.width, data.scene.height,
                                sh_degree=sh_degree, backgrounds=data.backgrounds[views],
                                render_mode="RGB+ED" if depth else "RGB", cpu_threads=self.config.render_threads or None)

    def render_views(self, viewmats: torch.Tensor, Ks: torch.Tensor | None = None,
                     params: dict[str, torch.Tensor] | None = None, sh_degree: int | None = None) -> torch.Tensor:
        """[B,H,W,3] renders of any cameras ([B,4,4] world-to-camera; intrinsics default to training view 0's) at
        the training size and background, of the Gaussians (default: this model's, e.g. perturbed copies), at
        `sh_degree` (default: the config's full degree)."""
        data, count = self.training_views, len(viewmats)
        Ks = data.Ks[:1].expand(count, 3, 3).contiguous() if Ks is None else Ks
        images, _, _ = render_gaussians(
            self.params if params is None else params, viewmats, Ks, data.scene.width, data.scene.height,
            sh_degree=self.config.sh_degree if sh_degree is None else sh_degree,
            backgrounds=data.backgrounds[:1].expand(count, 3), cpu_threads=self.config.render_threads or None,
        )
        return images

    def loss(self, views: torch.Tensor, viewmats: torch.Tensor, settings: StepSettings
             ) -> tuple[torch.Tensor, dict, dict]:
        """The training loss of views `views` ([B] long) rendered from [B,4,4] `viewmats`: (loss, its terms as
        floats, the render's meta with `means2d`'s gradient retained for densification)."""
        config, data = self.config, self.training_views
        # the depth map only while the depth term is on: without it the rasterizer's backward skips the depth terms
        with_depth = data.depths is not None and settings.depth
        chamfer = None
        if data.silhouettes is not None and settings.silhouette and config.lambda_chamfer > 0:
            # It needs no render, so it runs on a side thread while the render's host threads leave a core idle
            # between their stages: on the CPU it is small torch operations on one thread (a paper-preset step at
            # 108k Gaussians: 188-206 -> 177-193 ms). The same values as computed in line, and gradients summed in
            # the same order in every process (`beside_render`).
            chamfer = beside_render(
                data.silhouettes.chamfer_loss, self.params["means"], torch.sigmoid(self.params["opacities"]),
                viewmats, data.Ks[views], views.to(data.device))
        renders, alphas, meta = self.render(views, viewmats, settings.sh_degree, depth=with_depth)
        meta["means2d"].retain_grad()
        images, alphas = renders[..., :3], alphas[..., 0]
        targets = data.targets[views]
        blur = settings.blur_sigma
        if blur > 0:
            images, targets = gaussian_blur(images, blur), gaussian_blur(targets, blur)
        photometric, terms = photometric_loss(images, targets, config.lambda_dssim)
        loss = photometric
        if data.masks is not None and config.lambda_mask > 0:
            masks = data.masks[views]
            if blur > 0:
                alphas_blurred = gaussian_blur(alphas[..., None], blur)[..., 0]
                mask_term = mask_loss(alphas_blurred, gaussian_blur(masks[..., None], blur)[..., 0].clamp(0, 1))
            else:
                mask_term = mask_loss(alphas, masks)
            loss = loss + config.lambda_mask * mask_term
            terms["mask"] = mask_term.item()
        if data.silhouettes is not None and settings.silhouette:
            if config.lambda_mask_distance > 0:
                distance_term = data.silhouettes.distance_loss(alphas, views.to(data.device))
                loss = loss + config.lambda_mask_distance * distance_term
                terms["mask_distance"] = distance_term.item()
            if chamfer is not None:
                chamfer_term = chamfer()
                loss = loss + config.lambda_chamfer * chamfer_term
                terms["chamfer"] = chamfer_term.item()
        if with_depth:
            masks = None if data.masks is None else data.masks[views]
            depth_term = depth_loss(renders[..., 3], alphas, data.depths[views], masks, mode=config.depth_loss)
            if depth_term is not None:  # the photometric weight is 1 - lambda_depth while the depth term is on
                loss = loss + config.lambda_depth * depth_term - config.lambda_depth * photometric
                terms["depth"] = depth_term.item()
        return loss, terms, meta

    # ----------------------------------------------------------------------------------------------- optimization
    def set_learning_rate(self, fraction: float) -> None:
        """The position lr at `fraction` of its exponential schedule (the other groups keep theirs)."""
        lr = self.config.lr
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = exponential_lr(lr.means_init, lr.means_final, fraction) * self.scene_extent

    def sample_views(self) -> torch.Tensor:
        """[B] long: the training views of one step (`views_per_step` random ones, or all)."""
        per_step, count = self.config.views_per_step, self.training_views.num_views
        if per_step == 0 or per_step >= count:
            return torch.arange(count)
        return torch.randperm(count, generator=self.generator)[:per_step]

    def fit_step(self, cameras: CameraOptimizer, settings: StepSettings) -> tuple[torch.Tensor, dict]:
        """One coarse step: learning rate, sampled views, loss, Adam steps (the rendered cameras' too while
        `settings.pose_active`) and densification. Returns (loss, terms incl. densification counts).

        Raises:
            Diverged: the loss or a parameter is not finite (nothing was stepped).
        """
        self.set_learning_rate(settings.gaussian_lr_fraction)
        views = self.sample_views()
        loss, terms, meta = self.loss(views, cameras.poses(views, settings.pose_active), settings)
        matches = self.training_views.scene.matches
        if settings.pose_active and self.config.lambda_epipolar > 0 and matches is not None and len(matches):
            # the poses only: every camera's, though only the rendered ones take a step
            epipolar = epipolar_loss(cameras(), self.training_views.Ks, matches)
            loss = loss + self.config.lambda_epipolar * epipolar
            terms["epipolar"] = epipolar.item()
        self.optimize(loss, cameras, views, settings,
                      after_backward=lambda: self.strategy.accumulate(settings.round_iteration, meta))
        densified = self.strategy.step(settings.round_iteration + 1, self.params, self.optimizer, self.generator,
                                       grows=settings.densify)
        return loss, {**terms, **densified}

    def optimize(self, loss: torch.Tensor, cameras: CameraOptimizer, views: torch.Tensor, settings: StepSettings,
                 after_backward: Callable[[], None] | None = None) -> None:
        """Backward, one Adam step of the Gaussians and, where `settings.pose_active`, of the cameras `views` that
        `loss` rendered, whose corrections since the last rebase add `settings.pose_anchor` x
        `CameraOptimizer.anchor_loss` to the loss.

        Only the rendered cameras step (the others keep their values and moments); the gauge camera's gradient is
        zero.

        Raises:
            Diverged: the loss or a parameter is not finite (nothing was stepped).
        """
        if settings.pose_active and settings.pose_anchor > 0:
            loss = loss + settings.pose_anchor * cameras.anchor_loss(views)
        self._check_finite(loss, cameras)
        loss.backward()
        if after_backward is not None:
            after_backward()
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        if settings.pose_active:
            cameras.step(views)
        cameras.zero_grad()

    def _check_finite(self, loss: torch.Tensor, cameras: CameraOptimizer) -> None:
        if not torch.isfinite(loss):
            raise Diverged(f"loss is {loss.item()}")
        self.check_finite_parameters(cameras)

    def check_finite_parameters(self, cameras: CameraOptimizer) -> None:
        """Raise Diverged naming the first Gaussian parameter (or the cameras') with a NaN or infinite value."""
        named = [*self.params.items(), ("camera parameters", cameras.params())]
        # A sum is non-finite where any element is: one vectorized pass per tensor, in the tensor's own dtype (0.3
        # ms at 100k Gaussians with SH degree 2, against 2.5 summed in float64 and 5 for isfinite per element); the
        # element check runs only when a sum is non-finite, so a sum that overflows finite elements raises nothing.
        if torch.isfinite(torch.stack([param.detach().sum() for _, param in named])).all():
            return
        for name, param in named:
            if not torch.isfinite(param.detach()).all():
                raise Diverged(f"parameter {name} has NaN/inf values")

    # ----------------------------------------------------------------------------------------------- state
    def continue_from(self, other: GaussianModel) -> None:
        """Take over `other`'s Gaussians, their optimizer and densification state and scene extent (the training
        views stay this model's): how a leave-one-out model goes on with its left-out view added back."""
        self.strategy.scene_extent = other.scene_extent
        self.load_state_dict(copy.deepcopy(other.state_dict()))

    def state_dict(self) -> dict:
        """Checkpoint content: params (on the CPU), optimizer, strategy."""
        return {"params": {name: param.detach().cpu() for name, param in self.params.items()},
                "optimizer": self.optimizer.state_dict(), "strategy": self.strategy.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        device = self.training_views.device
        self.params = {name: torch.nn.Parameter(value.to(device)) for name, value in state["params"].items()}
        self.optimizer = gaussian_optimizer(self.params, self.config, self.scene_extent)
        self.optimizer.load_state_dict(state["optimizer"])
        # Checkpoints of earlier versions saved the per-tensor or foreach form, with the step count on the CPU.
        for group in self.optimizer.param_groups:
            group["foreach"], group["fused"] = None, True
        for param, param_state in self.optimizer.state.items():
            if "step" in param_state:
                param_state["step"] = param_state["step"].to(device=param.device, dtype=torch.float32)
        self.strategy.load_state_dict(state["strategy"])
