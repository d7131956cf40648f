"""Training presets for `warpbags train`: one typed dataclass, two named presets, CLI overrides on top.

`paper` follows the BAGS report's coarse schedule with GaussianObject's / 3DGS's Gaussian learning rates (the
dataclass defaults, stated once there) and its repair stage;
`quick` is a CPU-sized schedule (low resolution, few Gaussians, all views every step) for demos and tests.

It stays one module because it is one typed configuration: `TrainConfig` and the sections it nests, the two
presets written against them and the override parser that checks against the same fields.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
import typing
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, Literal

import torch

from warpbags.errors import WarpbagsError

BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}  # `TrainConfig.background`'s colours
ALIGNMENTS = ("procrustes", "pairwise")  # how estimated cameras are mapped onto reference ones (warpbags.alignment)
# The mean distance from the camera centres to the object centre after a scene's normalization (`warpbags.data`),
# the unit of the pose noise: 4.0 matches the NeRF-Synthetic (Blender) orbit (radius ~4.03), so BARF's pose-noise
# magnitudes (se(3) sigma 0.15) mean the same thing here.
ORBIT_RADIUS = 4.0
MAX_INIT_POINTS = 5_000_000  # initial Gaussians: 50x the paper preset's 100k, about 1 GB of parameters and moments
MAX_HULL_DILATION_PX = 100  # dilating every mask by more makes the hull the whole cube
MAX_HULL_RESOLUTION = 256  # the carving's first pass holds (1.5 x this)^3 voxel centres: 57 million, ~3 GB, at 256
# Host threads beyond a few per core only cost their start-up in every CPU render: 100000 took 17.5 s an iteration.
MAX_RENDER_THREADS = 1024
# Fields that the config.json of an earlier version's run holds and this version has not (experiments measured and
# reverted, docs/pose-recovery.md): such a run is still read (eval, export, render, view), not resumed.
RETIRED_FIELDS = ("camera.restarts", "camera.restart_margin", "camera.restart_turn_deg", "camera.coherence_max_miss",
                  "depth_patch", "pose_round_share")
# torch's CPU generators keep a seed modulo 2^32 (a negative one too): 2^32 trains as seed 0, -1 as 2^32 - 1.
SEEDS_END = 2**32
# The Gaussians' Adam runs in float32, below whose smallest normal number an epsilon is subnormal (which fast kernels
# flush to 0) or 0 itself: its first step then divides 0 by 0 wherever a gradient is 0 ("training diverged" at 1).
MIN_ADAM_EPS = torch.finfo(torch.float32).tiny
# The float fields that have a `warpbags train` option (cli/train_options.py's TRAIN_OPTIONS), by the name `--set`
# gives them: `TrainConfig.validate` names the option where a value is not finite, the others as `--set` spells them.
FLOAT_OPTIONS = {"rot_noise_deg": "--rot-noise-deg", "trans_noise": "--trans-noise", "blur_sigma_px": "--blur-px",
                 "camera.round_anchor": "--round-anchor"}


@dataclass(frozen=True)
class LearningRates:
    """Adam learning rates per parameter group (3DGS / GaussianObject defaults).

    Attributes:
        means_init, means_final: position lr at the first and last iteration of each coarse round (each round
            starts fresh Gaussians), times the scene extent, exponential decay in between; the repair stage keeps
            the final one. 3DGS's decay, over the run: GaussianObject's arguments keep 3DGS's 30k-step horizon
            for their 10k iterations, so theirs ends at about 3.4e-5, not 1.6e-6 (a review measured
            `--set lr.means_final=3.45e-4`, that share of a round, on maryrose: 300 quick iterations fit the
            views closer, the poses ended 1.4 deg further from the scene's).
        sh_dc, sh_rest: SH degree-0 and higher-degree coefficients.
        opacities: logit opacities.
        scales: log scales.
        quats: quaternions.
        adam_eps: Adam epsilon for the Gaussian groups, at least float32's smallest normal number (their Adam runs in
            float32).
        pose: pose-delta rotation lr when pose optimization starts.
        pose_final: pose-delta rotation lr at the end of each round's pose window (exponential decay over the
            window, as BARF, restarted every round); the repair stage keeps it.
        pose_translation_scale: translation lr = this x the rotation lr. Far from a small object a camera
            rotation and a sideways translation shift the image almost alike; a slower translation makes the
            optimizer explain shifts by rotation first (GaussianObject's COLMAP-free mode uses 1/3).
        pose_warmup: the pose lr ramps up linearly over the first this many steps of each round's pose window
            (from `pose_opt_start` where that falls later; 0 = none); the ramp multiplies the window's decay, so
            with it the lr peaks a little below `pose`.
            Adam's moments restart with every round, and its first steps move every latent by about the lr whatever
            the gradient: through the preconditioner that turns maryrose's cameras 4-8 deg about
            the object in one step (docs/pose-recovery.md).
    """

    means_init: float = 1.6e-4
    means_final: float = 1.6e-6
    sh_dc: float = 2.5e-3
    sh_rest: float = 2.5e-3 / 20
    opacities: float = 0.05
    scales: float = 5e-3
    quats: float = 1e-3
    adam_eps: float = 1e-15
    pose: float = 3e-3
    pose_final: float = 3e-4
    pose_translation_scale: float = 1.0
    pose_warmup: int = 0


@dataclass(frozen=True)
class DensifyConfig:
    """Adaptive density control (3DGS), run by `warpbags.strategy.DensifyStrategy`.

    Attributes:
        start, stop, every: densify (clone/split/prune) every `every` iterations in [start, stop) of each round,
            never at a round's last iteration (nothing would train the Gaussians it adds before the round's model is
            saved or scored and replaced; nor is the opacity reset done there).
        grad_threshold: mean view-space positional gradient norm (NDC-scaled, as 3DGS) above which a
            Gaussian is cloned (small) or split (large).
        percent_dense: the clone/split size boundary, as a fraction of the scene extent.
        prune_opacity: Gaussians below this opacity are removed.
        prune_scale: Gaussians whose largest scale exceeds this fraction of the scene extent are removed.
        opacity_reset_every: every this many iterations before `stop` opacities are clamped to 0.01 (0 = never);
            on a white background once more at `start`, as 3DGS and GaussianObject do.
        max_gaussians: no cloning/splitting beyond this count (0 = unlimited).
        floater_every: every this many iterations before `stop`, Gaussians far from their K = sqrt(N) nearest
            neighbours are removed (GaussianObject's floater removal, which also runs at `start` on a white
            background; 0 = never).
        floater_std_ratio: "far" = mean neighbour distance above average + this many standard deviations.
    """

    start: int = 500
    stop: int = 3000
    every: int = 100
    grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    prune_scale: float = 0.1
    opacity_reset_every: int = 1000
    max_gaussians: int = 0
    floater_every: int = 500
    floater_std_ratio: float = 3.0


@dataclass(frozen=True)
class CameraConfig:
    """How the pose corrections are parameterized and started (`warpbags.camera_optimizer`, `warpbags.silhouette`).

    Attributes:
        parameterization: "object" (rotation about the object centre, image shift, log depth: CamP's object-centric
            deltas) or "camera" (an se(3) twist about the camera centre, BARF's).
        precondition: CamP's preconditioner from the Jacobian of the projected initial points (computed once).
        precondition_reg: its damping r (CamP: 0.01-0.1).
        centroid_start: before anything else, turn each camera about its centre so that the ray through its mask
            centroid passes through the object centre (least-squares meeting point of those rays). Needs masks.
        coherence_iters: after the mask-centroid start, L-BFGS iterations that solve the cameras for silhouette
            coherence (every mask pixel's ray passes through the other views' silhouettes; `warpbags.silhouette`),
            before any Gaussian is fitted; 0 = off. Needs masks and pose optimization.
        coherence_continued_from_views: with this many training views or more, the solve measures the masks as
            continuing beyond the image border where they meet it (`SilhouetteTargets`, `continued_beyond_frame`);
            with fewer, the frame counts as background. Silhouettes fix n poses up to a similarity by the count of
            their epipolar tangencies from 6 views on (n (n - 1) against 6 n - 7); below that the frame's false
            border is a constraint the solve needs, above it the border pulls cameras away from poses at which a
            capture cut by the frame is coherent. 0 = always.
        coherence_epipolar: weight of the feature matches' epipolar residual (`TrainConfig.lambda_epipolar`) added to
            the silhouette-coherence solve's loss; 0 = off. The coherence loss is in image sizes and ends near
            1e-5 per other view; the residual is a mean Cauchy loss of about 0.1 at the reference poses and 1-2 a
            few degrees off.
        fix_first_camera: gauge; keep camera 0 at its starting pose (False: every camera is optimized and errors are
            measured after sim(3) alignment, the BAGS protocol).
        orbit_from_round: the object-centric orbit (wx, wy: the camera turned about the object centre, which stays
            put in its image) is optimized from this coarse round on (0-based; 0 = always, as CamP); before it only
            aim, roll, image shift and depth move. An orbit barely changes a distant object's image, and a
            half-fitted model lets cameras slide along it: on the near-cylindrical maryrose the cameras drift ~6 deg
            from the reference poses that way. A value of `rounds` or more keeps the orbit fixed to the end.
            Object parameterization only.
        round_anchor: from the second coarse round on, each step's loss adds round_anchor / 2 |delta|^2 averaged
            over the step's rendered cameras, delta a camera's corrections since its round started (in the
            parameterization's units: radians, focal lengths, log depth; in the repair stage, since the coarse
            stage's final poses): with B views per step, each camera pays 1/B of it. A round's fresh, half-fitted
            Gaussians pull the poses where they explain the images best, which on a real capture is partly along
            directions the images barely constrain; the anchor lets a later round move a camera only as far as the
            images pull it firmly (a proximal step; the first round, which starts far off, is free). 0 = off.
            Measured at 1 (15 deg / 0.3, 4 views, all rendered in every step: each pays 1/4; seeds 0-2): maryrose
            10.64 -> 8.13 deg, the telephoto synthetic scene 0.79 -> 2.89 (its later rounds gain by the same kind of
            moves), so off by default.
        lbfgs_from_round: from this coarse round on (0-based), the poses no longer take an Adam step with every
            Gaussian step: in the pose window, at every iteration i with i + 1 a multiple of `lbfgs_every` (counted
            from the start of training, not of the window) and at the window's last iteration, all training cameras
            are solved by `lbfgs_iters` L-BFGS iterations of the training loss against the current Gaussians, held
            fixed during the solve (`CameraOptimizer.refine`). Adam steps about its learning rate whatever the
            gradient's size and so moves the cameras along the directions the images barely constrain (an orbit
            about the object with the matching image shift); a solve moves them only as far as the loss goes down.
            None = Adam in every round. The repair stage keeps Adam; `round_anchor` does not enter the solves.
            Measured at 0 (15 deg / 0.3, 4 views, seeds 0-2): maryrose 10.65 -> 8.35 deg (its later rounds no
            longer drift), the telephoto synthetic scene 0.78 -> 0.94 with its exact depth maps and 1.19 -> 4.1
            (two seeds) with monocular-like ones (its later rounds gain less), so off by default.
        lbfgs_every, lbfgs_iters: how often the cameras are solved and the L-BFGS iterations of a solve.
        hypotheses_round: at the start of this coarse round (0-based; 0 or a round past the last = never; poses
            optimized only), the training camera whose view the last round's Gaussians fit worst is tried turned about
            the object centre (`hypothesis_axes`, `hypothesis_angles`). The unturned camera and each turn train the
            whole round from fresh Gaussians, and the turn of lowest mean loss over the round's last tenth is kept if
            that is below the unturned camera's by more than `hypothesis_margin`; training goes on from the kept trial
            (the issue's "outlier views"). The mask-centroid start fixes pan and tilt, not roll, and without depth maps
            a camera left 15-20 deg off in roll stays there, which the loss tells (telephoto synthetic scene, seed 0:
            0.083 against 0.075-0.076 for the seeds that converge). Costs one round per turn.
        hypothesis_axes, hypothesis_angles, hypothesis_margin: the axes of the camera's frame turned about, through
            the object centre ("z": parallel to the optical axis, a roll when the object is in the middle of the
            view; "x", "y": an orbit), the angles (degrees, each with both signs but 180), and the relative loss
            decrease a turn must bring to be kept.
        average_share: the final poses are the mean of the pose estimates after each step of the last coarse
            round's pose window, over its last `average_share` (chordal mean of the rotations, mean of the centres;
            Polyak's iterate averaging), instead of the last step's (0). Within a round the estimates wander with the
            Gaussians they are fitted with: the telephoto synthetic scene's cameras move 0.3-0.5 deg within 20
            iterations of the last round. The training itself is unchanged; only the poses it ends with are, and
            the Gaussians stay those fitted with the last estimate, 0.1-0.5 deg from the mean (held-out PSNR*
            measured 15.03 -> 14.43 on maryrose, 19.78 -> 19.51 on the Ethiopian Head, 20.94 on the synthetic scene
            either way). A repair stage after it starts from the mean with Adam's moments cleared.
    """

    parameterization: Literal["object", "camera"] = "object"
    precondition: bool = True
    precondition_reg: float = 0.1
    centroid_start: bool = True
    coherence_iters: int = 100
    coherence_continued_from_views: int = 6
    coherence_epipolar: float = 0.0
    fix_first_camera: bool = False
    orbit_from_round: int = 0
    round_anchor: float = 0.0
    lbfgs_from_round: int | None = None
    lbfgs_every: int = 10
    lbfgs_iters: int = 10
    hypotheses_round: int = 0
    hypothesis_axes: str = "z"
    hypothesis_angles: tuple[float, ...] = (15.0, 30.0)
    hypothesis_margin: float = 0.05
    average_share: float = 0.0


@dataclass(frozen=True)
class RepairConfig:
    """GaussianObject's second stage, run by `warpbags.repair` after the coarse iterations (`iters` 0 = off).

    Training pairs for the repairer (GaussianObject's leave_one_out_stage1/2 and dataset_lora, shortened so
    that a CPU run takes minutes; at the coarse-stage resolution, poses frozen at the coarse estimate):
        loo_iters: each leave-one-out model trains this many iterations in all (GaussianObject: 10000).
        loo_snapshot: the first `loo_snapshot` iterations see every training view but the left-out one
            (densification stops here; GaussianObject: 6000). From the snapshot, one copy goes on with the
            left-out view added and one without it; the per-channel mean/std of the difference between the two
            final models is the "3D noise" distribution.
        loo_samples: renders of the left-out view taken over the first quarter of the copy that sees it again
            (GaussianObject keeps ~25 of its left_image samples): the (corrupted render, real image) pairs.
        noise_renders: renders per training view of the coarse model with 3D noise added to positions, log
            scales, quaternions and logit opacities (noise ~ N(mean, std), clamped to mean +- c std for all but
            positions, c drawn from `noise_clamp_std`; each element kept with probability 1 - p, p drawn from
            `noise_dropout`; GaussianObject's add_statistics_noise with its ranges).

    Repairer (`warpbags.repair.network`):
        repairer: "unet" (a compact U-Net fitted per scene) or "package.module:factory" for a user's repairer
            (e.g. GaussianObject's ControlNet + LoRA with downloaded weights).
        unet_channels: channels of the U-Net's first level (doubled per level, 3 levels).
        fit_steps, fit_lr, fit_batch, fit_crop: Adam steps, learning rate, batch size and random crop size (px)
            for fitting the U-Net to the pairs (L1 loss).

    Repair optimization (GaussianObject's train_repair):
        iters: repair iterations after the coarse stage (paper: 3000; 0 = no repair stage).
        pseudo_views: novel cameras per refresh, each at a random point of a random gap between neighbouring
            training cameras (30-70% of the way; GaussianObject's sample_away_from_gt with 0.8).
        refresh_every: the pseudo cameras are redrawn and their repaired renders rebuilt this often.
        pseudo_ratio_start, pseudo_ratio_end, pseudo_until: loss = (1 - r) real + r pseudo, with r going
            linearly from start to end over the first `pseudo_until` fraction of the repair iterations and 0
            after (GaussianObject: 1.0 -> 0.5 over 2800 of 4000). The real-view term is the coarse loss as the
            coarse stage ended it (its silhouette terms where they were on; the depth term off) and drives the pose
            deltas; pseudo views never move the poses.
        weight_l1, weight_l2, weight_lpips: the pseudo-view loss mix (GaussianObject: 0.5 / 0.5 / 2.0; the LPIPS
            term only where the `lpips` package and its weights are available). Each pseudo view's loss is also
            scaled by min(1, 2 d / d_max), d its distance to the nearest training camera (GaussianObject).
        samples_kept: how many refreshes keep their sample strip in repair/samples.
    """

    iters: int = 0
    loo_iters: int = 300
    loo_snapshot: int = 200
    loo_samples: int = 4
    noise_renders: int = 8
    noise_clamp_std: tuple[float, float] = (0.6, 0.8)
    noise_dropout: tuple[float, float] = (0.6, 0.8)
    repairer: str = "unet"
    unet_channels: int = 16
    fit_steps: int = 400
    fit_lr: float = 2e-3
    fit_batch: int = 8
    fit_crop: int = 64
    pseudo_views: int = 8
    refresh_every: int = 50
    pseudo_ratio_start: float = 1.0
    pseudo_ratio_end: float = 0.5
    pseudo_until: float = 0.7
    weight_l1: float = 0.5
    weight_l2: float = 0.5
    weight_lpips: float = 2.0
    samples_kept: int = 3

    def checks(self) -> list[tuple[bool, str]]:
        """(condition, message) pairs for `TrainConfig.validate`."""
        span = (self.loo_iters - self.loo_snapshot) // 4
        between = lambda name, low, high: (  # noqa: E731
            low <= getattr(self, name) <= high, f"repair.{name} must be in [{low}, {high}], got {getattr(self, name)}")
        ranges = lambda name: (  # noqa: E731
            0 <= getattr(self, name)[0] <= getattr(self, name)[1] <= 1,
            f"repair.{name} must be (low, high) with 0 <= low <= high <= 1, got {getattr(self, name)}")
        return [
            (self.iters >= 0, f"--repair-iters must be >= 0, got {self.iters}"),
            (1 <= self.loo_snapshot < self.loo_iters,
             f"repair.loo_snapshot must be in [1, loo_iters), got {self.loo_snapshot}"),
            (1 <= self.loo_samples <= max(span, 1),
             f"repair.loo_samples must be in [1, (loo_iters - loo_snapshot) // 4 = {max(span, 1)}], got {self.loo_samples}"),
            (self.noise_renders >= 0, f"repair.noise_renders must be >= 0, got {self.noise_renders}"),
            ranges("noise_clamp_std"),
            ranges("noise_dropout"),
            (self.unet_channels > 0 and self.unet_channels % 4 == 0,
             f"repair.unet_channels must be a positive multiple of 4, got {self.unet_channels}"),
            (self.fit_steps >= 1, f"repair.fit_steps must be >= 1, got {self.fit_steps}"),
            (self.fit_lr > 0, f"repair.fit_lr must be > 0, got {self.fit_lr}"),
            (1 <= self.fit_batch <= 256, f"repair.fit_batch must be in [1, 256], got {self.fit_batch}"),
            (self.fit_crop >= 8, f"repair.fit_crop must be >= 8, got {self.fit_crop}"),
            (self.pseudo_views >= 1, f"repair.pseudo_views must be >= 1, got {self.pseudo_views}"),
            (self.refresh_every >= 1, f"repair.refresh_every must be >= 1, got {self.refresh_every}"),
            between("pseudo_ratio_start", 0, 1),
            between("pseudo_ratio_end", 0, 1),
            between("pseudo_until", 0, 1),
            (min(self.weight_l1, self.weight_l2, self.weight_lpips) >= 0, "repair loss weights must be >= 0"),
            (self.samples_kept >= 1, f"repair.samples_kept must be >= 1, got {self.samples_kept}"),
        ]


@dataclass(frozen=True)
class TrainConfig:
    """Everything that decides a training run (saved as config.json in the run folder).

    The defaults are the `paper` preset's coarse stage; only its repair stage differs from them.

    Attributes:
        preset: the preset this config came from.
        views: number of training views (the scene's sparse_{views}.txt split).
        iters: coarse-stage iterations (the repair stage adds `repair.iters` after them).
        rounds: the iterations are split into this many rounds; each round starts from fresh Gaussians (visual
            hull carved with the current poses) while the poses carry over, so Gaussians that absorbed pose
            errors are discarded and the hull sharpens as the poses improve (1 = the paper's single run). Ignored
            without pose optimization: the baseline trains one round with all the iterations. Rounds that do not
            divide the iterations differ by one iteration, the longer ones last.
        pose_opt: optimize per-camera pose deltas (False = GaussianObject's fixed-pose baseline).
        pose_opt_start: first iteration at which pose deltas are updated.
        pose_round_window: (start, end) shares of every round in which poses are updated; outside it only the
            Gaussians are (fresh Gaussians first fit the images before their gradients steer the poses, and a
            round can end fitting the Gaussians to the poses it found). (0, 1) = the whole round.
        pose_round_windows: one (start, end) per coarse round, the last repeated for later rounds; when given it
            replaces `pose_round_window`. () = `pose_round_window` in every round.
        depth_until: the depth term is used for each round's first `depth_until` iterations (0 = never).
        rot_noise_deg: injected rotation noise, std in degrees (an N(0, sigma^2) angle about a random axis).
        rot_noise_fixed: every camera turned by exactly `rot_noise_deg` (about a random axis) instead of a normal
            angle of that std: each camera starts that far off, none nearly right.
        trans_noise: injected camera-centre noise, std (N(0, sigma^2) per coordinate, in normalized scene units
            where the orbit radius is 4).
        noise_seed: seeds the injected pose noise, in [0, 2^32) (torch's CPU generator keeps a seed modulo 2^32).
        seed: seeds initialization and view sampling, in [0, 2^32).
        resolution: which image pyramid level to load (images_{resolution}); None = the scene preset's.
        max_image_size: images are further downscaled (area filter) so the longer side is at most this (0 = off).
        pyramid_levels: coarse-to-fine over rounds: with L levels the last round trains at the full (max_image_size)
            resolution, the one before at half of it, and so on for L rounds; earlier rounds stay at the coarsest
            level (1 = every round at full resolution).
        views_per_step: views rendered per iteration (0 = all training views; 1 = one random view, as 3DGS).
        background: "white" or "black"; the ground truth is masked onto it. GaussianObject's coarse stage draws a
            random one every step (`--random_background`), which ties the Gaussians' alpha to the masks; here the
            background stays fixed and `lambda_mask` weighs the rendered alpha against the masks instead.
        sh_degree: final SH degree; one degree is added every `sh_degree_every` iterations of each coarse round
            (each round's fresh Gaussians start at degree 0).
        init: "hull" (visual hull from masks and the current poses), "sfm" (the scene's SfM points, e.g. COLMAP's
            points3D) or "random" (uniform in the camera frusta's common bounds).
        init_points: number of initial Gaussians (hull voxels are subsampled / random points drawn to this).
        hull_resolution: voxels per axis of the carving grid.
        hull_dilation_px: masks are dilated by this many pixels (at the training resolution) before carving.
        hull_missed_views: a voxel may fall outside the (dilated) mask in this many views (GaussianObject: 1).
        blur_sigma_px: coarse-to-fine (BARF's idea in image space): renders, targets, alphas and masks are blurred
            with a Gaussian of this sigma (pixels) at each round's start, shrinking linearly to none at
            `blur_until` iterations into the round; a wide blur widens the basin of the photometric pose gradient
            (0 = off; measured 2.74 -> 2.60 deg on the 4-view synthetic scene at 10 deg, so off by default). A
            blur needs `blur_until` > 0.
        blur_until: iterations into each round at which the blur of `blur_sigma_px` has shrunk to none (0: no blur,
            and only with `blur_sigma_px` 0).
        lambda_dssim, lambda_mask, lambda_depth: loss weights (photometric weight is 1 - lambda_depth while
            the depth term is active).
        lambda_mask_distance: weight of mean(alpha * distance transform of the mask) (NeRS), a silhouette term
            whose pose gradient reaches cameras whose render misses the mask.
        lambda_chamfer: weight of the two-sided chamfer between projected Gaussian centres and mask edges (NeRS).
        silhouette_until: the two silhouette terms are used for each round's first `silhouette_until` iterations
            (0 = always).
        lambda_epipolar: weight of the feature matches' epipolar residual under the current poses
            (`warpbags.correspondences.epipolar_loss`: the mean Cauchy loss of their Sampson distances, in pixels at
            the training resolution) while the poses move; it acts on the poses only. The matches are SIFT matches
            between the training views at the resolution the scene is read at, from pairs of views whose
            fundamental matrix (MAGSAC) holds at least `matches_min_inliers` of them (`training_scene`). Views about
            90 deg apart share none, so with 4 views of an object the term finds nothing to do.
        matches_min_inliers: a pair of views gives matches only with at least this many inliers: a fundamental
            matrix fits 15-35 wrong matches of a pair by chance (`bench/view_matches.py`).
        depth_loss: "mad" (GaussianObject's median/MAD-normalized disparity L1) or "pearson" (1 - correlation).
        checkpoint_every: checkpoint interval in iterations.
        pose_alignment: alignment used for the logged pose error ("procrustes", "pairwise").
        render_threads: host threads for CPU rendering (0 = the renderer's default: all cores; at most
            `MAX_RENDER_THREADS`).
        repair: the repair stage that follows the `iters` coarse iterations (`repair.iters` = 0: none).
    """

    preset: str = "paper"
    views: int = 4
    iters: int = 5000
    rounds: int = 1
    pose_opt: bool = True
    pose_opt_start: int = 1000
    pose_round_window: tuple[float, float] = (0.0, 1.0)
    pose_round_windows: tuple[tuple[float, float], ...] = ()
    depth_until: int = 1000
    rot_noise_deg: float = 0.0
    rot_noise_fixed: bool = False
    trans_noise: float = 0.0
    noise_seed: int = 0
    seed: int = 0
    resolution: int | None = None
    max_image_size: int = 0
    pyramid_levels: int = 1
    views_per_step: int = 1
    background: Literal["white", "black"] = "white"
    sh_degree: int = 2
    sh_degree_every: int = 1000
    init: Literal["hull", "sfm", "random"] = "hull"
    init_points: int = 20000
    hull_resolution: int = 64
    hull_dilation_px: int = 0
    hull_missed_views: int = 1
    blur_sigma_px: float = 0.0
    blur_until: int = 0
    lambda_dssim: float = 0.2
    lambda_mask: float = 0.01
    lambda_depth: float = 0.05
    lambda_mask_distance: float = 0.0
    lambda_chamfer: float = 1.0
    silhouette_until: int = 0
    lambda_epipolar: float = 0.0
    matches_min_inliers: int = 40
    depth_loss: Literal["mad", "pearson"] = "mad"
    checkpoint_every: int = 500
    pose_alignment: Literal["procrustes", "pairwise"] = "procrustes"
    render_threads: int = 0
    lr: LearningRates = field(default_factory=LearningRates)
    camera: CameraConfig = field(default_factory=CameraConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    repair: RepairConfig = field(default_factory=RepairConfig)

    @property
    def background_rgb(self) -> tuple[float, float, float]:
        """The background colour Gaussians are trained, and shown, on."""
        return BACKGROUNDS[self.background]

    @property
    def total_iters(self) -> int:
        """Coarse plus repair iterations."""
        return self.iters + self.repair.iters

    @property
    def uses_matches(self) -> bool:
        """True when the poses are optimized with the feature matches' epipolar term, in training or in the
        silhouette-coherence solve: the training views' matches are then found before training."""
        return self.pose_opt and (self.lambda_epipolar > 0 or (self.camera.coherence_iters > 0
                                                               and self.camera.coherence_epipolar > 0))

    @property
    def injects_pose_noise(self) -> bool:
        """True when noise is added to the scene's poses (an experiment: the scene's poses are the truth). Without
        it training starts from the scene's own poses, and the distance from them is a correction, not an error."""
        return self.rot_noise_deg > 0 or self.trans_noise > 0

    def validate(self) -> TrainConfig:
        """Check value ranges; returns self.

        Raises:
            WarpbagsError: the first out-of-range value, named as its CLI option, or setting that would do nothing
                (--blur-px without --blur-until); a float that is not finite (NaN, inf) anywhere in the config,
                nested groups and lists included, before any range.
        """
        non_finite = _non_finite(self)
        if non_finite is not None:
            name, value = non_finite
            if isinstance(value, tuple):
                raise WarpbagsError(f"{name} must be finite numbers, got {list(value)}")
            raise WarpbagsError(f"{FLOAT_OPTIONS.get(name, name)} must be a finite number, got {value}")
        checks = [
            (self.views >= 2, f"--views must be >= 2, got {self.views}"),  # a visual hull needs two
            (self.iters >= 1, f"--iters must be >= 1, got {self.iters}"),
            (1 <= self.rounds <= self.iters, f"--rounds must be in [1, iters], got {self.rounds}"),
            (self.camera.orbit_from_round >= 0,
             f"camera.orbit_from_round must be >= 0, got {self.camera.orbit_from_round}"),
            (self.camera.orbit_from_round == 0 or self.camera.parameterization == "object",
             "camera.orbit_from_round needs the object parameterization (--camera-param object)"),
            (self.camera.round_anchor >= 0, f"camera.round_anchor must be >= 0, got {self.camera.round_anchor}"),
            (self.camera.lbfgs_from_round is None or (type(self.camera.lbfgs_from_round) is int
                                                      and self.camera.lbfgs_from_round >= 0),
             f"camera.lbfgs_from_round must be >= 0 or null, got {self.camera.lbfgs_from_round}"),
            (self.camera.lbfgs_every >= 1, f"camera.lbfgs_every must be >= 1, got {self.camera.lbfgs_every}"),
            (self.camera.hypotheses_round >= 0,
             f"camera.hypotheses_round must be >= 0, got {self.camera.hypotheses_round}"),
            (len(self.camera.hypothesis_axes) > 0 and set(self.camera.hypothesis_axes) <= set("xyz")
             and len(set(self.camera.hypothesis_axes)) == len(self.camera.hypothesis_axes),
             f"camera.hypothesis_axes must be different letters of xyz, got {self.camera.hypothesis_axes!r}"),
            (len(self.camera.hypothesis_angles) > 0 and all(0 < angle <= 180 for angle in self.camera.hypothesis_angles)
             and len(set(self.camera.hypothesis_angles)) == len(self.camera.hypothesis_angles),
             f"camera.hypothesis_angles must be different degrees in (0, 180] (each turned both ways, 180 once), got "
             f"{list(self.camera.hypothesis_angles)}"),
            (0 <= self.camera.hypothesis_margin < 1,
             f"camera.hypothesis_margin must be in [0, 1), got {self.camera.hypothesis_margin}"),
            (0 <= self.camera.average_share <= 1,
             f"camera.average_share must be in [0, 1], got {self.camera.average_share}"),
            (self.camera.lbfgs_iters >= 1, f"camera.lbfgs_iters must be >= 1, got {self.camera.lbfgs_iters}"),
            (self.camera.coherence_iters >= 0,
             f"camera.coherence_iters must be >= 0, got {self.camera.coherence_iters}"),
            (self.camera.coherence_continued_from_views >= 0,
             f"camera.coherence_continued_from_views must be >= 0, got {self.camera.coherence_continued_from_views}"),
            (self.pose_opt_start >= 0, f"--pose-opt-start must be >= 0, got {self.pose_opt_start}"),
            (self.rot_noise_deg > 0 or not self.rot_noise_fixed,
             "--rot-noise-fixed needs --rot-noise-deg > 0 (the angle every camera is turned by)"),
            (_is_window(self.pose_round_window),
             f"pose_round_window must be (start, end) with 0 <= start < end <= 1, got {self.pose_round_window}"),
            (all(_is_window(window) for window in self.pose_round_windows),
             "pose_round_windows must be a list of (start, end) with 0 <= start < end <= 1, got "
             f"{self.pose_round_windows}"),
            (self.rot_noise_deg >= 0, f"--rot-noise-deg must be >= 0, got {self.rot_noise_deg}"),
            (self.rot_noise_deg <= 180, f"--rot-noise-deg must be <= 180, got {self.rot_noise_deg}"),
            (self.trans_noise >= 0, f"--trans-noise must be >= 0, got {self.trans_noise}"),
            (self.trans_noise <= ORBIT_RADIUS,
             f"--trans-noise must be <= {ORBIT_RADIUS:g} (a std in normalized scene units, where the cameras orbit at "
             f"radius {ORBIT_RADIUS:g}), got {self.trans_noise}"),
            *((0 <= getattr(self, name) < SEEDS_END,
               f"--{name.replace('_', '-')} must be in [0, 2^32), got {getattr(self, name)}: torch's CPU generator "
               f"keeps a seed modulo 2^32, so it would act as seed {getattr(self, name) % SEEDS_END}")
              for name in ("seed", "noise_seed")),
            (self.depth_until >= 0, f"depth_until must be >= 0, got {self.depth_until}"),
            (self.resolution in (None, 1, 2, 4, 8), f"--resolution must be 1, 2, 4 or 8, got {self.resolution}"),
            (self.max_image_size == 0 or self.max_image_size >= 16,
             f"--max-image-size must be 0 (off) or >= 16 (smaller images leave too few pixels to fit), got "
             f"{self.max_image_size}"),
            (self.pyramid_levels >= 1, f"pyramid_levels must be >= 1, got {self.pyramid_levels}"),
            (0 <= self.views_per_step <= self.views,
             f"views_per_step must be in [0, views = {self.views}] (0 = all), got {self.views_per_step}"),
            (self.background in BACKGROUNDS, f"background must be white or black, got {self.background!r}"),
            (0 <= self.sh_degree <= 3, f"sh_degree must be 0-3, got {self.sh_degree}"),
            (self.sh_degree_every >= 1, f"sh_degree_every must be >= 1, got {self.sh_degree_every}"),
            (self.init in ("hull", "sfm", "random"), f"--init must be hull, sfm or random, got {self.init!r}"),
            (1 <= self.init_points <= MAX_INIT_POINTS,
             f"init_points must be in [1, {MAX_INIT_POINTS}], got {self.init_points}"),
            (2 <= self.hull_resolution <= MAX_HULL_RESOLUTION,
             f"hull_resolution must be in [2, {MAX_HULL_RESOLUTION}] (its first pass carves (1.5 x this)^3 voxels), "
             f"got {self.hull_resolution}"),
            (0 <= self.hull_dilation_px <= MAX_HULL_DILATION_PX,
             f"hull_dilation_px must be in [0, {MAX_HULL_DILATION_PX}], got {self.hull_dilation_px}"),
            (self.hull_missed_views >= 0, f"hull_missed_views must be >= 0, got {self.hull_missed_views}"),
            (self.checkpoint_every >= 1, f"checkpoint_every must be >= 1, got {self.checkpoint_every}"),
            (self.blur_sigma_px >= 0, f"--blur-px must be >= 0, got {self.blur_sigma_px}"),
            (self.blur_until >= 0, f"--blur-until must be >= 0, got {self.blur_until}"),
            # the blur shrinks to none over blur_until iterations: with 0 it is never applied
            (self.blur_sigma_px == 0 or self.blur_until > 0,
             f"--blur-px {self.blur_sigma_px:g} needs --blur-until > 0 (the iterations into each round over which the "
             "blur shrinks to none), got --blur-until 0"),
            (0 <= self.lambda_dssim <= 1, f"lambda_dssim must be in [0, 1], got {self.lambda_dssim}"),
            (self.lambda_mask >= 0, f"lambda_mask must be >= 0, got {self.lambda_mask}"),
            (0 <= self.lambda_depth < 1, f"lambda_depth must be in [0, 1), got {self.lambda_depth}"),
            (self.depth_loss in ("mad", "pearson"), f"--depth-loss must be mad or pearson, got {self.depth_loss!r}"),
            (self.pose_alignment in ALIGNMENTS, f"pose_alignment: {self.pose_alignment!r}"),
            (0 <= self.render_threads <= MAX_RENDER_THREADS, f"render_threads must be in [0, {MAX_RENDER_THREADS}] "
             f"(0: all cores), got {self.render_threads}"),
            (self.camera.parameterization in ("object", "camera"),
             f"camera.parameterization must be object or camera, got {self.camera.parameterization!r}"),
            (self.camera.precondition_reg > 0, f"camera.precondition_reg must be > 0, got {self.camera.precondition_reg}"),
            (self.lr.pose_warmup >= 0, f"lr.pose_warmup must be >= 0, got {self.lr.pose_warmup}"),
            # the exponential schedules interpolate in log space: their ends must be positive
            *((getattr(self.lr, name) > 0, f"lr.{name} must be > 0, got {getattr(self.lr, name)}")
              for name in ("means_init", "means_final", "pose", "pose_final")),
            (self.lr.adam_eps >= MIN_ADAM_EPS, f"lr.adam_eps must be >= {MIN_ADAM_EPS}, the smallest normal "
             f"float32 (the Gaussians' Adam divides by it in float32, where a smaller one may be 0), got "
             f"{self.lr.adam_eps}"),
            *((getattr(self.lr, name) >= 0, f"lr.{name} must be >= 0, got {getattr(self.lr, name)}")
              for name in ("sh_dc", "sh_rest", "opacities", "scales", "quats", "pose_translation_scale")),
            (self.densify.every >= 1, f"densify.every must be >= 1, got {self.densify.every}"),
            (0 <= self.densify.start <= self.densify.stop,
             f"densify.start and densify.stop must be 0 <= start <= stop, got {self.densify.start} and "
             f"{self.densify.stop}"),
            (self.densify.grad_threshold > 0,
             f"densify.grad_threshold must be > 0, got {self.densify.grad_threshold}"),
            (self.densify.percent_dense >= 0, f"densify.percent_dense must be >= 0, got {self.densify.percent_dense}"),
            (0 <= self.densify.prune_opacity < 1,
             f"densify.prune_opacity must be in [0, 1), got {self.densify.prune_opacity}"),
            (self.densify.prune_scale > 0, f"densify.prune_scale must be > 0, got {self.densify.prune_scale}"),
            (self.densify.max_gaussians >= 0,
             f"densify.max_gaussians must be >= 0 (0: unlimited), got {self.densify.max_gaussians}"),
            (self.densify.floater_std_ratio >= 0,
             f"densify.floater_std_ratio must be >= 0, got {self.densify.floater_std_ratio}"),
            (min(self.densify.floater_every, self.densify.opacity_reset_every) >= 0,
             "densify.floater_every and densify.opacity_reset_every must be >= 0 (0: never)"),
            (min(self.lambda_mask_distance, self.lambda_chamfer) >= 0, "silhouette loss weights must be >= 0"),
            (self.silhouette_until >= 0, f"silhouette_until must be >= 0, got {self.silhouette_until}"),
            (min(self.lambda_epipolar, self.camera.coherence_epipolar) >= 0,
             "lambda_epipolar and camera.coherence_epipolar must be >= 0"),
            (self.matches_min_inliers >= 8, f"matches_min_inliers must be >= 8, got {self.matches_min_inliers}"),
            *self.repair.checks(),
            (self.repair.iters == 0 or self.views >= 3, "the repair stage needs at least 3 training views"),
            (self.repair.iters == 0 or self.background == "white",
             "the repair stage works on a white background (GaussianObject's), got background black"),

        ]
        for ok, message in checks:
            if not ok:
                raise WarpbagsError(message)
        return self

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def replaced(self, **overrides: Any) -> TrainConfig:
        """This config with fields replaced (the groups lr, camera, densify and repair may be given as partial
        dicts), type-checked and validated as a whole.

        Raises:
            WarpbagsError: an unknown field, a value of the wrong type, or an out-of-range value.
        """
        return _replaced(self, overrides).validate()

    @staticmethod
    def from_dict(values: dict[str, Any]) -> TrainConfig:
        """The config `to_dict` wrote (e.g. a run's config.json); fields it lacks keep their defaults.

        Raises:
            WarpbagsError: an unknown field or a value of the wrong type.
        """
        values = dict(values)
        for _, group, key in list(_retired_places(values)):  # read as this version has them: not at all
            if group:
                values[group] = {field: value for field, value in values[group].items() if field != key}
            else:
                del values[key]
        if "fix_first_camera" in values:  # before the camera group existed (runs of warpbags <= 2026-11)
            values["camera"] = {**values.get("camera", {}), "fix_first_camera": values.pop("fix_first_camera")}
        # Saved before `validate` refused them, so that such a run still resumes: a blur without blur_until was
        # never applied, more render threads than MAX_RENDER_THREADS only cost time, and a seed outside [0, 2^32)
        # acted as its remainder.
        if values.get("blur_until", 0) == 0 and values.get("blur_sigma_px"):
            values["blur_sigma_px"] = 0.0
        if isinstance(values.get("render_threads"), int) and values["render_threads"] > MAX_RENDER_THREADS:
            values["render_threads"] = MAX_RENDER_THREADS
        for name in ("seed", "noise_seed"):  # seeds outside [0, 2^32) trained as torch kept them: modulo 2^32
            if isinstance(values.get(name), int) and not isinstance(values[name], bool):
                values[name] %= SEEDS_END
        return _replaced(TrainConfig(), values)


def paper() -> TrainConfig:
    """The BAGS report's schedule: the `TrainConfig` defaults, which state its coarse stage (5000 iterations, poses
    from 1000, depth until 1000, one view per step, 3DGS densification and learning rates), then 3000 repair
    iterations (`RepairConfig`'s defaults are a short CPU-sized stage, off)."""
    return TrainConfig(
        # The report's repair stage; leave-one-out models use the coarse recipe (GaussianObject keeps its
        # leave-one-out Gaussian set fixed from iteration 6000 of 10000: here from the densification stop).
        repair=RepairConfig(iters=3000, loo_iters=5000, loo_snapshot=3000, loo_samples=8, unet_channels=32,
                            fit_steps=2000, fit_crop=128, pseudo_views=20, refresh_every=200),
    )


def quick() -> TrainConfig:
    """CPU-sized: ~128 px images, <= 6000 Gaussians, all views every step, 600 iterations in 3 rounds.

    The paper's schedule compressed for 2 cores, with what made pose recovery work from 15 deg / 0.3 noise on every
    camera (4 views; mean rotation error after sim(3) alignment, single-seed exploration runs of
    `bench/pose_recovery.py SCENE --seeds 0 --set ...`; docs/pose-recovery.md has the full tables):
    - the object-centric, preconditioned camera parameterization (`camera`): synthetic 14.2 -> 1.86 deg, against
      7.03 for an se(3) twist about the camera centre;
    - the chamfer between projected Gaussian centres and mask edges (lambda_chamfer 1): synthetic 1.86 -> 0.91;
    - poses updated from a quarter into each round to its end (pose_round_window): the fresh Gaussians of a round
      first fit the images. On maryrose, poses started *at the truth* drift 6-10 deg within 20 iterations when
      they move from a round's first iteration, and stay within 0.5 deg once the Gaussians have fitted the images
      for 200 iterations. Measured windows (synthetic / maryrose): the first half 0.81 / 17.0 deg, the second
      half 12.2 / 3.47, from a quarter on 1.39 / 7.75 (kept: the only one that helps both; the BAGS report too
      starts its poses a fifth into training). With the coherence solve in front (eighteenth session, seeds 0-2),
      from half-way: synthetic 0.84 (exact maps) / 2.11 (none), maryrose 7.44, moldgoldcape 7.21, against 0.67 /
      1.64, 8.85, 8.86 from a quarter: better on both real captures, worse on the synthetic scene, so not changed;
    - the depth term (where the scene has depth maps) for the first half of each round, half of it while the poses
      move (depth_until 100; 60 before): synthetic 1.33 -> 0.65 deg with its exact depth maps, 1.74 -> 1.17 with them
      degraded as a monocular network's (`bench/pose_recovery.py --depth monocular`; the whole round: 0.60 and 1.56,
      the centres 2.3% off). Per-view depth maps tie each camera to the shape, which a fresh model fitting four
      images does not: without them the synthetic scene ends at 5.6 deg (`--depth none`), and maryrose has none;
    - three rounds of 200 iterations, each re-carving the hull with the improved poses and starting fresh
      Gaussians; rotation lr 1e-2 -> 1e-3 with a 10x slower translation (equal rates: no better, 1.55 vs 1.51);
    - the pose lr ramped up over the first 20 steps of each round's pose window (lr.pose_warmup): Adam's first step
      after the moments restart turned maryrose's cameras 4-8 deg about the object. Seeds 0-2: synthetic exact maps
      0.78 -> 0.62 deg, monocular-like 1.19 -> 1.11, none 5.37 -> 5.19; maryrose 10.65 -> 10.47 (each within the
      seeds' spread, none worse).
    - at the start of round 2, the camera the first round's Gaussians fit worst is tried turned about the object
      centre, about its optical axis, by +-15 and +-30 deg, each turn training round 2 from fresh Gaussians; the lowest loss is
      kept if 5% below the unturned camera's (`camera.hypotheses_round`; 2.3x the training iterations). Seeds 0-2,
      where a camera was left 15-20 deg off in roll: synthetic without depth maps 5.19 -> 1.96 deg, under changing
      light 5.89 -> 4.14, at 30 deg / 0.3 with exact maps 4.39 -> 0.78; with exact or monocular-like maps at 15 deg
      and on maryrose no turn is kept and the results are unchanged (0.62, 1.11, 10.47).
    - the final poses are the mean of the last round's pose estimates (`camera.average_share` 1.0; thirty-first
      session, `bench/pose_recovery.py --seeds 0,1,2` and `3,4,5`): synthetic exact maps, six seeds 0.62 -> 0.55
      deg; maryrose 8.46 -> 7.96; the Ethiopian Head 9.55 -> 9.57.
    Not kept: NeRS's alpha x distance-transform term (0.81 -> 0.88 deg; normalized by the rendered mass it
    diverged, 20 deg); a lower pose lr (3e-3: synthetic 4.3 deg after 300 iterations instead of 1.2); a pose lr
    warm-up instead of the window (maryrose still drifts 7 deg from the truth in 20 iterations).
    """
    return TrainConfig(
        preset="quick",
        iters=600,
        rounds=3,
        pose_opt_start=0,
        pose_round_window=(0.25, 1.0),
        depth_until=100,
        checkpoint_every=100,
        max_image_size=128,
        views_per_step=0,
        sh_degree=0,
        init_points=3000,
        hull_resolution=48,
        hull_dilation_px=2,
        lr=LearningRates(means_init=1.6e-3, means_final=1.6e-5, pose=1e-2, pose_final=1e-3,
                         pose_translation_scale=0.1, pose_warmup=20),
        # 4x the 3DGS threshold: until the statistics were scaled by the views per step, the quick preset's 4-view
        # batches densified at this effective threshold, and every measurement above was taken with it.
        densify=DensifyConfig(start=100, stop=201, every=50, grad_threshold=8e-4, opacity_reset_every=0,
                              max_gaussians=6000, floater_every=0),
        camera=CameraConfig(hypotheses_round=1, average_share=1.0),
    )


PRESETS = {"paper": paper, "quick": quick}
DEFAULT_PRESET = "quick"  # what `warpbags train` and `warpbags sweep` train with unless --preset says otherwise


def _is_window(value: Any) -> bool:
    """(start, end) shares of a round with 0 <= start < end <= 1."""
    numbers = isinstance(value, tuple) and len(value) == 2 and all(
        isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)
    return numbers and 0 <= value[0] < value[1] <= 1


def _non_finite(config: Any, prefix: str = "") -> tuple[str, Any] | None:
    """The first field of a config dataclass, its nested groups' included, that holds a float that is not finite
    (itself or, for a tuple, any item at any depth), as (dotted name, value); None when there is none."""
    for item in dataclasses.fields(config):
        value = getattr(config, item.name)
        if dataclasses.is_dataclass(value):
            found = _non_finite(value, f"{prefix}{item.name}.")
            if found is not None:
                return found
        elif not _finite(value):
            return prefix + item.name, value
    return None


def _finite(value: Any) -> bool:
    """False for a float that is NaN or infinite, or a tuple holding one at any depth; True for anything else."""
    if isinstance(value, float):
        return math.isfinite(value)
    return all(_finite(item) for item in value) if isinstance(value, tuple) else True


def is_number(value: Any) -> bool:
    """Whether `value`, read from JSON, is a number: an int or a float, not a bool (JSON's true is no number, though
    Python's bool is an int). Config fields, log records and eval.json are read through it."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


_KINDS = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}


def _is_kind(value: Any, kind: Any) -> bool:
    """Whether `value` passes for a field of the plain type `kind` (ints for floats; a bool is no int)."""
    if kind is float:
        return is_number(value)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, kind) if isinstance(kind, type) else True


def _typed(value: Any, default: Any, name: str, declared: Any) -> Any:
    """`value` as the type of the field's `default` (ints pass for floats, lists for tuples), the field declared as
    `declared`. An empty tuple default, or a field declared `tuple[T, ...]`, takes a list of any length (nested lists
    become tuples; `TrainConfig.validate` checks the items, which must be numbers where T is float). A field that may be
    None (`int | None`) takes None or a value of its other type, checked against the declaration: the default None
    tells nothing."""
    if (default == () or _any_length_tuple(declared)) and isinstance(value, (list, tuple)):
        value = tuple(tuple(item) if isinstance(item, list) else item for item in value)
        if typing.get_args(declared)[:1] == (float,) and not all(is_number(item) for item in value):
            raise WarpbagsError(f"{name} must be a list of numbers, got {list(value)}")
        return value
    if default is None or value is None:
        union = typing.get_origin(declared) in (typing.Union, types.UnionType)
        kinds = [kind for kind in typing.get_args(declared) if kind is not type(None)] if union else [declared]
        if value is None and union and type(None) in typing.get_args(declared):
            return value
        if value is not None and any(_is_kind(value, kind) for kind in kinds):
            return value
        if default is not None:
            raise WarpbagsError(f"{name} must be like {default!r}, got {value!r}")
        what = " or ".join(_KINDS.get(kind, getattr(kind, "__name__", str(kind))) for kind in kinds)
        raise WarpbagsError(f"{name} must be {what} or null, got {value!r}")
    if isinstance(default, bool) or not isinstance(default, (int, float, tuple)):
        ok = isinstance(value, type(default))
    elif isinstance(default, float):
        ok = is_number(value)
    elif isinstance(default, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, (list, tuple)) and len(value) == len(default)
        value = tuple(value) if ok else value
        if ok and all(map(is_number, default)):  # a pair of numbers takes numbers only
            ok = all(map(is_number, value))
    if not ok:
        raise WarpbagsError(f"{name} must be like {default!r}, got {value!r}")
    return value


def _any_length_tuple(declared: Any) -> bool:
    """Whether a field's declared type is `tuple[T, ...]`."""
    return typing.get_origin(declared) is tuple and typing.get_args(declared)[-1:] == (Ellipsis,)


def _replaced(base: Any, overrides: dict[str, Any], prefix: str = "") -> Any:
    """`base` (a config dataclass) with fields replaced, nested groups given as partial dicts, types checked."""
    fields = typing.get_type_hints(type(base))  # the declared types, resolved (annotations are strings here)
    unknown = set(overrides) - set(fields)
    if unknown:
        raise WarpbagsError(f"unknown training option(s): {', '.join(prefix + key for key in sorted(unknown))}")
    changes = {}
    for key, value in overrides.items():
        current = getattr(base, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise WarpbagsError(f"{prefix}{key} must be a group of fields, got {value!r}")
            changes[key] = _replaced(current, value, f"{prefix}{key}.")
        else:
            changes[key] = _typed(value, current, prefix + key, fields[key])
    return dataclasses.replace(base, **changes)


def differing_fields(saved: dict[str, Any], current: dict[str, Any], ignored: frozenset[str] = frozenset(),
                     prefix: str = "") -> list[tuple[str, Any, Any]]:
    """(field, saved value, current value) for each field two configs' `to_dict()`s both hold and set differently,
    named as `--set` names it ("lr.pose", not the group "lr"), sorted by name; fields named in `ignored` and fields only
    one holds (a config of a warpbags that had fewer) are left out. Lists and tuples compare alike: a config read
    back from JSON holds lists where the dataclass holds tuples."""
    differences = []
    for key in saved.keys() & current.keys() - ignored:
        if isinstance(saved[key], dict) and isinstance(current[key], dict):
            differences += differing_fields(saved[key], current[key], ignored, f"{prefix}{key}.")
        elif _as_lists(saved[key]) != _as_lists(current[key]):
            differences.append((prefix + key, saved[key], current[key]))
    return sorted(differences)


def _as_lists(value: Any) -> Any:
    return [_as_lists(item) for item in value] if isinstance(value, (list, tuple)) else value


def parse_settings(settings: list[str]) -> dict[str, Any]:
    """"name=value" / "group.name=value" strings as `load_preset` overrides: "a=1" -> {"a": 1},
    "repair.b=2" -> {"repair": {"b": 2}}. Values are JSON (numbers, true/false, lists); anything else is a string.

    Raises:
        WarpbagsError: an item without "=", a group's field after the group was set to a value, the preset (chosen
            by --preset: a `--set` relabelled the run without changing its schedule), or a field set to null
            outside a group (`load_preset` takes None as "the preset's value": it was ignored silently).
    """
    overrides: dict[str, Any] = {}
    for item in settings:
        key, separator, text = item.partition("=")
        if not separator or "" in key.split("."):  # no name, or a group or field of no name (".pose=1")
            raise WarpbagsError(f"--set {item!r}: expected name=value or group.name=value")
        if key == "preset":
            raise WarpbagsError(f"--set {item!r}: the preset is chosen by --preset, which sets every other field")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        group, _, name = key.rpartition(".")
        if value is None and not group:
            raise WarpbagsError(f"--set {item!r}: null is not a value of {key}; leave it out for the preset's")
        if group:
            fields = overrides.setdefault(group, {})
            if not isinstance(fields, dict):
                raise WarpbagsError(f"--set {item!r}: {group} was set to {fields!r}, not a group of fields")
            fields[name] = value
        else:
            overrides[key] = value
    return overrides


def retired_fields(values: dict[str, Any]) -> list[str]:
    """The `RETIRED_FIELDS` that a saved config's `values` (`TrainConfig.to_dict`'s of an earlier version) hold."""
    return [name for name, _, _ in _retired_places(values)]


def _retired_places(values: dict[str, Any]) -> Iterator[tuple[str, str, str]]:
    """(name, group, key) of each of the `RETIRED_FIELDS` that `values` hold: `values[group][key]`, or `values[key]`
    where the group is ''."""
    for name in RETIRED_FIELDS:
        group, _, key = name.rpartition(".")
        settings = values.get(group) if group else values
        if isinstance(settings, dict) and key in settings:
            yield name, group, key


def check_repairer_used(overrides: dict[str, Any], config: TrainConfig, option: str = "--repairer") -> None:
    """Raise when `overrides` (`load_preset`'s, which made `config`) name a repairer that `config` never builds: with
    the repair stage off it would be silently unused.

    Args:
        option: how the command names the repairer in the message (`warpbags sweep` sets it only by --set).

    Raises:
        WarpbagsError: `repair.repairer` given and `repair.iters` 0.
    """
    repair = overrides.get("repair")
    if isinstance(repair, dict) and "repairer" in repair and config.repair.iters == 0:
        raise WarpbagsError(f"{option} {config.repair.repairer} would be unused: the repair stage is off "
                            "(repair.iters is 0); add --repair-iters N")


def load_preset(name: str, **overrides: Any) -> TrainConfig:
    """A preset by name with fields replaced (None values are ignored; the groups lr, camera, densify and repair may be
    given as partial dicts), type-checked and validated.

    Raises:
        WarpbagsError: unknown preset or field, a value of the wrong type, or an out-of-range value.
    """
    if name not in PRESETS:
        raise WarpbagsError(f"--preset must be one of {', '.join(PRESETS)}, got {name!r}")
    return PRESETS[name]().replaced(**{key: value for key, value in overrides.items() if value is not None})
