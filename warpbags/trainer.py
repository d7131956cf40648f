"""`Trainer`: joint optimization of 3D Gaussians and per-camera pose deltas (BAGS), coarse then repair stage.

One class for every variant (pose optimization on/off, gauge choice, repair on/off, presets) chosen by
`TrainConfig`. The first `iters` iterations are the coarse stage; the `repair.iters` after them the repair stage
(`warpbags.repair.RepairStage`: pseudo views supervised by repaired renders, next to the real views).

The run folder's files (config, poses, log, checkpoints, results) are written by `warpbags.run_folder.RunFolder`,
whose docstring gives the layout.
"""

from __future__ import annotations

import contextlib
import copy
import math
import signal
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from warpbags.configs.train import TrainConfig
from warpbags.data.noise import PoseNoise, noisy_viewmats
from warpbags.data.scene import Scene
from warpbags.errors import WarpbagsError
from warpbags.gaussians import render_gaussians
from warpbags.init import hull_or_random_points, initial_gaussians
from warpbags.losses import depth_loss, gaussian_blur, mask_loss, photometric_loss
from warpbags.camera_optimizer import CameraOptimizer, CameraOptimizerSettings, exponential_lr
from warpbags.alignment import pose_errors
from warpbags.cameras import camera_centers
from warpbags.repair import RepairStage, repairer_factory
from warpbags.repair.stage import pseudo_ratio
from warpbags.run_folder import RunFolder
from warpbags.silhouette import SilhouetteTargets, centroid_start, rays_meeting_point
from warpbags.strategy import DensifyStrategy
from warpbags.threads import torch_threads


class Trainer:
    """Gaussians + pose deltas from the training views of one scene.

    Args:
        scene: the scene, already restricted to the training views (``Scene.subset``) and downscaled; its
            ``viewmats`` are the true poses.
        config: the training configuration.
        out_dir: run folder (created when first written).
        device: "cpu" or "cuda".
        viewmats_init: [C,4,4] starting poses; default: the true poses with the config's noise injected.
        log: callable receiving a one-line notice (e.g. "no depth maps: depth term skipped").
    """

    def __init__(self, scene: Scene, config: TrainConfig, out_dir: str | Path, device: str = "cpu",
                 viewmats_init: torch.Tensor | None = None, log: Callable[[str], None] = print):
        if device == "cuda" and not torch.cuda.is_available():
            raise WarpbagsError("--device cuda: no CUDA device is available")
        if device not in ("cpu", "cuda"):
            raise WarpbagsError(f"--device must be cpu or cuda, got {device!r}")
        if config.repair.iters > 0:
            repairer_factory(config.repair.repairer)  # a bad --repairer fails now, not after the coarse stage
        self.config, self.device, self.log = config, torch.device(device), log
        self.run_folder = RunFolder(out_dir)
        self.num_cameras = scene.num_views
        to = dict(device=self.device)
        self.full_scene = scene
        self._levels: dict[int, Scene] = {}  # the scene at each pyramid level used so far
        self._use_level(0)
        self.viewmats_true = scene.viewmats.to(**to)
        if viewmats_init is None:
            noise = PoseNoise(config.rot_noise_deg, config.trans_noise, config.noise_seed)
            viewmats_init = noisy_viewmats(scene, noise)
            if config.camera.fix_first_camera:
                # The gauge camera defines the world frame (as the first camera in bundle adjustment): it is
                # taken as known, since its delta stays zero and its noise could never be corrected.
                viewmats_init[0] = scene.viewmats[0]
        self.viewmats_init = viewmats_init.to(**to).float()
        self.viewmats_start, self.object_center = self._starting_poses()
        centers = camera_centers(self.viewmats_init)
        self.scene_extent = 1.1 * float((centers - centers.mean(0)).norm(dim=-1).max())
        if self.depths is None and config.depth_until > 0:
            self.log("no depth maps in this scene: depth term skipped")

        self.generator = torch.Generator().manual_seed(config.seed)
        self.iteration = 0
        # The camera optimizer is created exactly once (resume loads state into it); its preconditioner comes from
        # the first round's initial points.
        self.cameras: CameraOptimizer | None = None
        self._start_round()
        settings = CameraOptimizerSettings.from_config(config.camera, lr=config.lr.pose,
                                                       translation_scale=config.lr.pose_translation_scale)
        self.cameras = CameraOptimizer(self.viewmats_start, settings, self.object_center, self.Ks, self.scene.width,
                                       self.scene.height, self.params["means"].detach())
        self.repair_stage: RepairStage | None = None  # built when the repair stage first uses pseudo views
        self._repair_state: dict | None = None  # its checkpointed state, applied when it is built
        self._stop_requested = False

    # ----------------------------------------------------------------------------------------------- setup
    def _use_level(self, level: int) -> None:
        """Train at pyramid level `level` from now on (0 = the full training resolution, k = 1/2^k of it): images,
        masks, depths, intrinsics, masked targets and silhouette targets at that size."""
        config, to = self.config, dict(device=self.device)
        full = self.full_scene
        if level not in self._levels:
            self._levels[level] = full if level == 0 else full.downscaled(max(8, max(full.width, full.height) >> level))
        scene = self._levels[level]
        if getattr(self, "scene", None) is scene:
            return
        self.scene = scene
        self.images = scene.images.to(**to)
        self.masks = None if scene.masks is None else scene.masks.to(**to)
        self.depths = None if scene.depths is None else scene.depths.to(**to)
        self.Ks = scene.Ks.to(**to)
        background = 1.0 if config.background == "white" else 0.0
        self.backgrounds = torch.full((self.num_cameras, 3), background, **to)
        if self.masks is not None:  # GaussianObject: the object on a plain background
            m = self.masks[..., None]
            self.targets = self.images * m + background * (1 - m)
        else:
            self.targets = self.images
        self.silhouettes = None
        if self.masks is not None and (config.lambda_mask_distance > 0 or config.lambda_chamfer > 0):
            self.silhouettes = SilhouetteTargets(self.masks).to(self.device)

    def pyramid_level(self) -> int:
        """The current round's level: with L levels, round r of R trains at 1/2^(L-1-r) of the resolution (never
        finer than full), so the last rounds are at full resolution; the repair stage is too."""
        if self.in_repair:
            return 0
        rounds = math.ceil(self.config.iters / self.round_length)
        current = min(self.iteration // self.round_length, rounds - 1)  # a finished run stays in its last round
        return min(self.config.pyramid_levels - 1, rounds - 1 - current)

    def _starting_poses(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The poses the optimization starts from and the object centre (world) the cameras agree on.

        With masks and `camera.centroid_start`, each camera is first turned so that its mask-centroid ray passes
        through the rays' meeting point. Without masks the centre is where the optical axes (nearly) meet.
        """
        viewmats = self.viewmats_init
        if self.masks is not None and self.config.camera.centroid_start and self.config.pose_opt:
            start, center = centroid_start(self.masks.cpu(), viewmats.cpu(), self.Ks.cpu())
            return start.to(viewmats), center.to(viewmats)
        if self.masks is None and self.config.camera.centroid_start and self.config.pose_opt:
            self.log("no masks: no mask-centroid start")
        axes = viewmats[:, 2, :3].double().cpu()  # camera z axes in world coordinates
        center = rays_meeting_point(camera_centers(viewmats).double().cpu(), axes)
        return viewmats.clone(), center.to(viewmats)

    def _start_round(self) -> None:
        """Fresh Gaussians (visual hull carved with the current poses), their optimizer and densification state.

        Called at iteration 0 and at each later round's first iteration: the poses carry over, the Gaussians
        (which have partly absorbed the old pose errors) do not.
        """
        self._use_level(self.pyramid_level())
        self.params = self._initial_params()
        self.optimizer = self._make_optimizer()
        self.strategy = DensifyStrategy(self.config.densify, self.scene_extent)

    def _initial_params(self) -> dict[str, torch.nn.Parameter]:
        config = self.config
        points, colors, note = hull_or_random_points(
            self.images.cpu(), None if self.masks is None else self.masks.cpu(), self.current_viewmats().cpu(),
            self.Ks.cpu(), method=config.init, count=config.init_points, resolution=config.hull_resolution,
            dilation_px=config.hull_dilation_px, missed_views=config.hull_missed_views, generator=self.generator,
            sfm_points=self.scene.points, sfm_colors=self.scene.point_colors,
        )
        self.log(f"initialization: {note}")
        raw = initial_gaussians(points, colors, config.sh_degree)
        return {name: torch.nn.Parameter(value.to(self.device)) for name, value in raw.items()}

    def _make_optimizer(self) -> torch.optim.Adam:
        lr = self.config.lr
        rates = {"means": lr.means_init * self.scene_extent, "scales": lr.scales, "quats": lr.quats,
                 "opacities": lr.opacities, "sh0": lr.sh_dc, "shN": lr.sh_rest}
        groups = [{"params": [param], "lr": rates[name], "name": name} for name, param in self.params.items()]
        return torch.optim.Adam(groups, lr=0.0, eps=lr.adam_eps)

    # ----------------------------------------------------------------------------------------------- state
    @property
    def round_length(self) -> int:
        # Rounds re-carve the hull with improved poses; with frozen poses (the baseline) they would only throw
        # trained Gaussians away, so the baseline trains one round with the whole budget.
        rounds = self.config.rounds if self.config.pose_opt else 1
        return math.ceil(self.config.iters / rounds)

    @property
    def round_iteration(self) -> int:
        """Iterations done in the current round (Gaussian schedules restart with each round)."""
        return self.iteration % self.round_length

    @property
    def in_repair(self) -> bool:
        """True in the repair stage: the coarse iterations are done and repair iterations follow."""
        return self.config.repair.iters > 0 and self.iteration >= self.config.iters

    def sh_degree(self) -> int:
        if self.in_repair:
            return self.config.sh_degree
        return min(self.config.sh_degree, self.round_iteration // max(self.config.sh_degree_every, 1))

    def blur_sigma(self) -> float:
        """Coarse-to-fine blur (pixels) at the current iteration."""
        config = self.config
        if config.blur_until <= 0 or self.in_repair:
            return 0.0
        return config.blur_sigma_px * max(0.0, 1.0 - self.round_iteration / config.blur_until)

    def pose_active(self) -> bool:
        """Poses are updated from `pose_opt_start` on, inside `pose_round_window` of every coarse round (and in the
        repair stage)."""
        if not self.config.pose_opt or self.iteration < self.config.pose_opt_start:
            return False
        start, end = self._pose_window()
        return self.in_repair or start <= self.iteration < end

    def _pose_window(self) -> tuple[int, int]:
        """[start, end) iterations of the current round in which poses are updated (`pose_round_window`, no
        earlier than `pose_opt_start`)."""
        config = self.config
        round_start = self.iteration - self.round_iteration
        window_start, window_end = config.pose_round_window
        start = max(round_start + math.ceil(window_start * self.round_length), config.pose_opt_start)
        return start, min(round_start + math.ceil(window_end * self.round_length), config.iters)

    def current_viewmats(self) -> torch.Tensor:
        """[C,4,4] the poses as currently estimated (the starting poses before the camera optimizer exists)."""
        return self.viewmats_start if self.cameras is None else self.cameras.viewmats()

    def pose_error(self, viewmats: torch.Tensor | None = None) -> dict[str, float]:
        """Mean rotation (deg) and camera-centre errors of `viewmats` (default: current) against the truth."""
        viewmats = self.current_viewmats() if viewmats is None else viewmats
        if self.num_cameras < 3 and self.config.pose_alignment == "procrustes":
            alignment = "pairwise"
        else:
            alignment = self.config.pose_alignment
        errors = pose_errors(viewmats.double().cpu(), self.viewmats_true.double().cpu(), alignment=alignment)
        return {"rot_err_deg": errors["rotation_error_deg_mean"], "trans_err": errors["translation_error_mean"]}

    def _set_learning_rates(self) -> None:
        config, fraction = self.config, self.round_iteration / max(self.round_length - 1, 1)
        if self.in_repair:  # GaussianObject's repair keeps the final position lr; the poses keep their final lr
            fraction = 1.0
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = exponential_lr(config.lr.means_init, config.lr.means_final, fraction) * self.scene_extent
        # The pose lr decays within each round's pose window (a warm restart per round: each round is a fresh
        # coarse-to-fine fit).
        pose_start, pose_end = self._pose_window()
        pose_fraction = 1.0 if self.in_repair else (self.iteration - pose_start) / max(pose_end - pose_start - 1, 1)
        self.cameras.set_learning_rate(exponential_lr(config.lr.pose, config.lr.pose_final, pose_fraction))

    # ----------------------------------------------------------------------------------------------- step
    def _views(self) -> torch.Tensor:
        per_step = self.config.views_per_step
        if per_step == 0 or per_step >= self.num_cameras:
            return torch.arange(self.num_cameras)
        return torch.randperm(self.num_cameras, generator=self.generator)[:per_step]

    def render_views(self, viewmats: torch.Tensor, Ks: torch.Tensor | None = None,
                     params: dict[str, torch.Tensor] | None = None) -> torch.Tensor:
        """[B,H,W,3] renders of any cameras ([B,4,4] world-to-camera, intrinsics default camera 0's) at the
        training size and background, of the Gaussians (default: the trainer's own, e.g. perturbed copies)."""
        count = len(viewmats)
        Ks = self.Ks[:1].expand(count, 3, 3).contiguous() if Ks is None else Ks
        images, _, _ = render_gaussians(
            self.params if params is None else params, viewmats, Ks, self.scene.width, self.scene.height,
            sh_degree=self.sh_degree(), backgrounds=self.backgrounds[:1].expand(count, 3),
            cpu_threads=self.config.render_threads or None,
        )
        return images

    def render(self, views: torch.Tensor, pose_grad: bool = True, sh_degree: int | None = None):
        """Render training views `views` ([B] long) at the current poses; returns (colors, alphas, meta)."""
        viewmats = self.cameras.apply(views) if pose_grad else self.cameras.viewmats()[views]
        return render_gaussians(
            self.params, viewmats, self.Ks[views], self.scene.width, self.scene.height,
            sh_degree=self.sh_degree() if sh_degree is None else sh_degree, backgrounds=self.backgrounds[views],
            render_mode="RGB+ED", cpu_threads=self.config.render_threads or None,
        )

    def _loss(self, views: torch.Tensor) -> tuple[torch.Tensor, dict, dict]:
        config = self.config
        renders, alphas, meta = self.render(views, pose_grad=self.pose_active())
        meta["means2d"].retain_grad()
        images, depths, alphas = renders[..., :3], renders[..., 3], alphas[..., 0]
        targets = self.targets[views]
        blur = self.blur_sigma()
        if blur > 0:
            images, targets = gaussian_blur(images, blur), gaussian_blur(targets, blur)
        photometric, terms = photometric_loss(images, targets, config.lambda_dssim)
        loss = photometric
        if self.masks is not None and config.lambda_mask > 0:
            masks = self.masks[views]
            if blur > 0:
                alphas_blurred = gaussian_blur(alphas[..., None], blur)[..., 0]
                mask_term = mask_loss(alphas_blurred, gaussian_blur(masks[..., None], blur)[..., 0].clamp(0, 1))
            else:
                mask_term = mask_loss(alphas, masks)
            loss = loss + config.lambda_mask * mask_term
            terms["mask"] = mask_term.item()
        silhouette_active = config.silhouette_until <= 0 or self.round_iteration < config.silhouette_until
        if self.silhouettes is not None and silhouette_active and not self.in_repair:
            if config.lambda_mask_distance > 0:
                distance_term = self.silhouettes.distance_loss(alphas, views.to(self.device))
                loss = loss + config.lambda_mask_distance * distance_term
                terms["mask_distance"] = distance_term.item()
            if config.lambda_chamfer > 0:
                chamfer_term = self.silhouettes.chamfer_loss(
                    self.params["means"], torch.sigmoid(self.params["opacities"]), meta["viewmats"], self.Ks[views],
                    views.to(self.device))
                loss = loss + config.lambda_chamfer * chamfer_term
                terms["chamfer"] = chamfer_term.item()
        depth_active = not self.in_repair and self.round_iteration < config.depth_until and config.lambda_depth > 0
        if self.depths is not None and depth_active:
            depth_term = depth_loss(depths, alphas, self.depths[views], None if self.masks is None else self.masks[views],
                                    mode=config.depth_loss)
            if depth_term is not None:
                loss = loss + config.lambda_depth * depth_term - config.lambda_depth * photometric
                terms["depth"] = depth_term.item()
        return loss, terms, meta

    def _check_finite(self, loss: torch.Tensor) -> None:
        bad = None if torch.isfinite(loss) else f"loss is {loss.item()}"
        if bad is None:
            for name, param in [*self.params.items(), ("camera parameters", self.cameras.params().detach())]:
                if not torch.isfinite(param).all():
                    bad = f"parameter {name} has NaN/inf values"
                    break
        if bad is not None:
            last = self.latest_checkpoint()
            kept = f"last good checkpoint: {last}" if last else "no checkpoint was written yet"
            raise WarpbagsError(f"training diverged at iteration {self.iteration}: {bad}; {kept}")

    def train_step(self) -> dict:
        """One iteration (coarse or repair stage); returns its log record."""
        if self.in_repair:
            return self._repair_step()
        started = time.perf_counter()
        if self.iteration > 0 and self.round_iteration == 0:
            self._start_round()
            # Same optimizer object, moments cleared on purpose: the pose lr restarts with the round, and Adam's
            # second moments from the converged end of the last round would turn its first steps into jumps.
            self.cameras.reset_moments()
        self._set_learning_rates()
        views = self._views()
        loss, terms, meta = self._loss(views)
        self._optimize(loss, views, after_backward=lambda: self.strategy.accumulate(self.round_iteration, meta))
        densify = self.strategy.step(self.round_iteration or self.round_length, self.params, self.optimizer,
                                     self.generator)
        return self._record("coarse", loss, {**terms, **densify}, started)

    def _optimize(self, loss: torch.Tensor, views: torch.Tensor | None,
                  after_backward: Callable[[], None] | None = None) -> None:
        """Backward, one Adam step of the Gaussians and (while active) of the rendered cameras `views` (None: no
        real view was rendered), then the iteration count."""
        self._check_finite(loss)
        loss.backward()
        if after_backward is not None:
            after_backward()
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        # Only the rendered cameras step (the others keep their values and moments); the gauge camera's gradient
        # is zero.
        if self.pose_active() and views is not None:
            self.cameras.step(views)
        self.cameras.zero_grad()
        self.iteration += 1

    def _record(self, stage: str, loss: torch.Tensor, terms: dict, started: float) -> dict:
        return {"iter": self.iteration, "stage": stage, "loss": loss.item(), **terms,
                "num_gaussians": len(self.params["means"]), "sh_degree": self.sh_degree(),
                "pose_opt": self.pose_active(), **self.pose_error(), "seconds": time.perf_counter() - started}

    def _repair_step(self) -> dict:
        """A repair-stage iteration: (1 - r) real-view loss + r pseudo-view loss, no densification."""
        started = time.perf_counter()
        ratio = pseudo_ratio(self.config.repair, self.iteration - self.config.iters)
        if self.repair_stage is None and ratio > 0:  # built when first needed (no pairs for a real-only schedule)
            self.repair_stage = RepairStage(self, self.log)
            if self._repair_state is not None:
                self.repair_stage.load_state_dict(self._repair_state)
        self._set_learning_rates()
        loss, terms, views = torch.zeros((), device=self.device), {"pseudo_ratio": ratio}, None
        if ratio < 1:
            views = self._views()
            real, real_terms, _ = self._loss(views)
            loss, terms = (1 - ratio) * real, {**terms, **real_terms}
        if ratio > 0:
            pseudo, pseudo_terms = self.repair_stage.loss(self)
            loss, terms = loss + ratio * pseudo, {**terms, **pseudo_terms}
        self._optimize(loss, views)
        return self._record("repair", loss, terms, started)

    def continue_from(self, other: Trainer) -> None:
        """Take over `other`'s Gaussians, their optimizer and densification state, iteration and scene extent (the
        poses stay this trainer's): how a leave-one-out model goes on with its left-out view added back."""
        self.scene_extent, self.iteration = other.scene_extent, other.iteration
        self.params = {name: torch.nn.Parameter(value.detach().clone()) for name, value in other.params.items()}
        self.optimizer = self._make_optimizer()
        self.optimizer.load_state_dict(copy.deepcopy(other.optimizer.state_dict()))
        self.strategy.load_state_dict(copy.deepcopy(other.strategy.state_dict()))

    # ----------------------------------------------------------------------------------------------- files
    @property
    def out_dir(self) -> Path:
        return self.run_folder.path

    def latest_checkpoint(self) -> Path | None:
        return self.run_folder.latest_checkpoint()

    def save_checkpoint(self) -> Path:
        return self.run_folder.save_checkpoint({
            "iteration": self.iteration,
            "config": self.config.to_dict(),
            "params": {name: param.detach().cpu() for name, param in self.params.items()},
            "optimizer": self.optimizer.state_dict(),
            "cameras": self.cameras.state(),
            "strategy": self.strategy.state_dict(),
            "generator": self.generator.get_state(),
            "viewmats_init": self.viewmats_init.cpu(),
            "repair": None if self.repair_stage is None else self.repair_stage.state_dict(),
        })

    def load_checkpoint(self, path: Path) -> None:
        """Restore everything a checkpoint holds (into the existing pose parameter and optimizer objects).

        Raises:
            WarpbagsError: the checkpoint is unreadable or from an older warpbags.
        """
        state = self.run_folder.load_checkpoint(path, self.device)
        self.iteration = state["iteration"]
        self.params = {name: torch.nn.Parameter(value.to(self.device)) for name, value in state["params"].items()}
        self.optimizer = self._make_optimizer()
        self.optimizer.load_state_dict(state["optimizer"])
        self.cameras.load_state(state["cameras"])
        self.strategy.load_state_dict(state["strategy"])
        self.generator.set_state(state["generator"])
        self.viewmats_init = state["viewmats_init"].to(self.device)
        self.viewmats_start = self.cameras.viewmats_init
        self._use_level(self.pyramid_level())
        self.repair_stage, self._repair_state = None, state.get("repair")

    def resume(self) -> bool:
        """Load the newest checkpoint and cut log.jsonl back to it; False when there is none."""
        path = self.latest_checkpoint()
        if path is None:
            return False
        self.load_checkpoint(path)
        self.run_folder.truncate(self.iteration)
        self.log(f"resumed from {path} (iteration {self.iteration})")
        return True

    def write_run_files(self, extra: dict | None = None, folder: Path | None = None) -> None:
        """config.json, poses_true/init/start.npy, intrinsics.npy into `folder` (default: the run folder)."""
        run_folder = self.run_folder if folder is None else RunFolder(folder)
        # The full training resolution, whatever level a round trains at.
        run_folder.write_setup(self.config, self.full_scene, str(self.device), self.viewmats_true, self.viewmats_init,
                               self.viewmats_start, extra)

    def write_results(self, folder: Path | None = None) -> None:
        """gaussians.ply and poses_final.npy into `folder` (default: the run folder)."""
        (self.run_folder if folder is None else RunFolder(folder)).write_results(self.params, self.current_viewmats())

    # ----------------------------------------------------------------------------------------------- loop
    def _request_stop(self, signum, frame) -> None:
        self._stop_requested = True

    @property
    def stop_requested(self) -> bool:
        """Ctrl-C was pressed: long work inside a step (building repair pairs) stops early."""
        return self._stop_requested

    def train(self, stop_at: int | None = None, callback: Callable[[dict], None] | None = None) -> dict:
        """Train until `stop_at` (default: all coarse and repair iterations) are done; returns the last record.

        Checkpoints every `checkpoint_every` iterations, at the end of the coarse stage and at the end. With a
        repair stage, the coarse result is also written to coarse/ as a run folder of its own. Ctrl-C (SIGINT)
        finishes the current iteration, saves a checkpoint and raises KeyboardInterrupt. Divergence raises
        WarpbagsError.
        """
        total = self.config.total_iters
        stop_at = total if stop_at is None else min(stop_at, total)
        previous_handler = None
        try:
            previous_handler = signal.signal(signal.SIGINT, self._request_stop)
        except ValueError:  # not the main thread: Ctrl-C is handled by the caller
            pass
        record: dict = {}
        # On the CPU Warp runs its own host threads; torch's OpenMP workers would fight them.
        threads = torch_threads(1) if self.device.type == "cpu" else contextlib.nullcontext()
        try:
            with threads, self.run_folder.log_writer() as write_log:
                while self.iteration < stop_at:
                    record = self.train_step()
                    write_log(record)
                    if callback is not None:
                        callback(record)
                    coarse_done = self.iteration == self.config.iters and self.config.repair.iters > 0
                    if coarse_done:
                        self.write_run_files(folder=self.out_dir / "coarse")
                        self.write_results(self.out_dir / "coarse")
                    if self.iteration % self.config.checkpoint_every == 0 or self.iteration == stop_at or coarse_done:
                        self.save_checkpoint()
                    if self._stop_requested:
                        self.save_checkpoint()
                        raise KeyboardInterrupt
        finally:
            if previous_handler is not None:
                signal.signal(signal.SIGINT, previous_handler)
        if self.iteration >= total:
            self.write_results()
        return record


def training_scene(scene: Scene | str | Path, config: TrainConfig, data_root: str | Path | None = None,
                   log: Callable[[str], None] | None = None) -> Scene:
    """The training views of a scene (a loaded Scene, a preset name or a folder), downscaled per `config`.

    The views are the scene's `sparse_{views}.txt` split, or else a farthest-point choice (said through `log`).

    Raises:
        WarpbagsError: unknown scene, missing data, or fewer images than `config.views`.
    """
    if not isinstance(scene, Scene):
        from warpbags.data import open_scene

        scene = open_scene(scene, root=data_root, resolution=config.resolution)
    views = scene.train_views(config.views)
    if log is not None and str(config.views) not in scene.splits:
        log(f"{scene.name} has no sparse_{config.views}.txt: {config.views} training views chosen by farthest-point "
            "sampling of the camera centres")
    return scene.subset(views).downscaled(config.max_image_size)


def default_run_dir(scene_name: str, views: int, root: str | Path = "runs") -> Path:
    """`runs/<scene>-<views>v-<YYYYmmdd-HHMMSS>`."""
    return Path(root) / f"{scene_name}-{views}v-{time.strftime('%Y%m%d-%H%M%S')}"


def start_or_resume(scene: Scene, config: TrainConfig, out_dir: str | Path, device: str = "cpu", resume: bool = False,
                    log: Callable[[str], None] = print) -> Trainer:
    """A Trainer for `out_dir`: fresh (run files written) or, with `resume`, continued from its last checkpoint
    (with the config saved in the run folder).

    Raises:
        WarpbagsError: `resume` without a checkpoint in `out_dir`, or a fresh run into a folder that has one.
    """
    run_folder = RunFolder(out_dir)
    if resume:
        if not run_folder.has_checkpoint():
            raise WarpbagsError(f"--resume: no checkpoint in {run_folder.checkpoints}")
        config = run_folder.saved_config()
    elif run_folder.has_checkpoint():
        raise WarpbagsError(f"{out_dir} already holds a run; pass --resume to continue it or choose another --out")
    trainer = Trainer(scene, config, out_dir, device=device, log=log)
    if resume:
        trainer.resume()
    else:
        trainer.write_run_files()
    return trainer
