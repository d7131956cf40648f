"""The repairer's training data, built as GaussianObject builds it from the scene's own failures.

* Leave-one-out pairs: for each training view, a model trained without it renders it; the (corrupted render,
  real image) pair shows what a sparse-view model gets wrong about an unseen view.
* 3D-noise pairs: the coarse model with noise on its Gaussians renders the training views. The noise follows the
  per-channel statistics of how a leave-one-out model's Gaussians differ from those of a copy that did see the
  view, so renders fail the way unseen views fail, while the real image is known.

Everything runs at the coarse stage's resolution with the poses frozen at its estimate; `RepairConfig` documents
the schedule and how it maps onto GaussianObject's.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch

from warpbags.camera_setup import starting_poses, training_cameras
from warpbags.configs.train import TrainConfig
from warpbags.errors import WarpbagsError
from warpbags.files import atomic_output
from warpbags.model import Diverged, GaussianModel, TrainingViews, scene_extent
from warpbags.schedule import Schedule

# Parameters that get 3D noise (GaussianObject's add_statistics_noise leaves colours alone).
NOISY_PARAMETERS = ("means", "scales", "quats", "opacities")
LEAVE_ONE_OUT, NOISE = "leave-one-out", "3d-noise"


@dataclass
class NoiseStatistics:
    """Per-channel mean and std of (unseen - seen) Gaussian parameters, averaged over the leave-one-out models.

    Attributes:
        mean, std: parameter name -> tensor of one row's shape (e.g. [3] for means).
    """

    mean: dict[str, torch.Tensor]
    std: dict[str, torch.Tensor]


@dataclass
class RepairPairs:
    """(corrupted render, real image) pairs on a white background.

    Attributes:
        corrupted, targets: [P, H, W, 3] float32 in [0, 1].
        kinds: P labels, LEAVE_ONE_OUT or NOISE.
        views: P training-view indices the pairs show (the repairer holds one view out to choose its fit).
        noise: the 3D-noise statistics the NOISE pairs were drawn with.
    """

    corrupted: torch.Tensor
    targets: torch.Tensor
    kinds: list[str]
    views: list[int]
    noise: NoiseStatistics

    def select(self, keep: list[bool]) -> RepairPairs:
        """The pairs where `keep` is true."""
        index = [i for i, kept in enumerate(keep) if kept]
        return RepairPairs(self.corrupted[index], self.targets[index], [self.kinds[i] for i in index],
                           [self.views[i] for i in index], self.noise)

    def save(self, path: Path) -> None:
        with atomic_output(path) as temporary:
            torch.save(dataclasses.asdict(self), temporary)

    @staticmethod
    def load(path: Path) -> RepairPairs:
        state = torch.load(path, map_location="cpu", weights_only=False)
        return RepairPairs(**{**state, "noise": NoiseStatistics(**state["noise"])})


def leave_one_out_config(config: TrainConfig) -> TrainConfig:
    """The coarse config turned into a leave-one-out run: `loo_iters` single-round iterations with frozen poses
    (the caller passes the coarse estimate) and no repair stage; the Gaussian set is fixed from `loo_snapshot` on."""
    repair = config.repair
    densify = dataclasses.replace(config.densify, stop=min(config.densify.stop, repair.loo_snapshot), floater_every=0)
    return dataclasses.replace(config, iters=repair.loo_iters, rounds=1, pose_opt=False, densify=densify,
                               repair=dataclasses.replace(repair, iters=0))


class LeaveOneOutFit:
    """Gaussians fitted to some training views with their poses frozen: a `GaussianModel` and the (never stepped)
    camera optimizer it renders through, on the coarse schedule of a leave-one-out config. No run folder.

    Args:
        config: a `leave_one_out_config`.
        training_views: the views it fits.
        viewmats: [C,4,4] their frozen poses.
    """

    def __init__(self, config: TrainConfig, training_views: TrainingViews, viewmats: torch.Tensor):
        self.schedule, self.iteration = Schedule(config), 0
        viewmats = viewmats.float()
        start, center = starting_poses(viewmats, training_views.masks, training_views.Ks, config, log=_silent)
        generator = torch.Generator().manual_seed(config.seed)  # each fit draws its own initialization and views
        self.model = GaussianModel.initialized(config, training_views, start, scene_extent(viewmats), generator,
                                               log=_silent)
        self.cameras = training_cameras(config, start, center, training_views.Ks, training_views.scene.width,
                                        training_views.scene.height, self.model.params["means"].detach())

    def continue_from(self, other: LeaveOneOutFit) -> None:
        """Go on from `other`'s Gaussians, optimizer state and iteration, fitting this fit's views."""
        self.model.continue_from(other.model)
        self.iteration = other.iteration

    def train_until(self, iteration: int, should_stop: Callable[[], bool]) -> None:
        """Coarse steps until `iteration` are done.

        Raises:
            KeyboardInterrupt: `should_stop()` turned true (checked every iteration).
            WarpbagsError: the fit diverged.
        """
        while self.iteration < iteration:
            if should_stop():
                raise KeyboardInterrupt
            try:
                self.model.fit_step(self.cameras, self.schedule.at(self.iteration))
            except Diverged as error:
                raise WarpbagsError(f"a leave-one-out fit diverged at iteration {self.iteration}: {error}") from None
            self.iteration += 1

    def render(self, view: int) -> torch.Tensor:
        """[H, W, 3] CPU render of view `view` at its pose and the schedule's SH degree (no gradient)."""
        return _render(self.model, self.cameras.viewmats(), view, sh_degree=self.schedule.sh_degree(self.iteration))


def _silent(message: str) -> None:
    """Leave-one-out fits say nothing (the coarse run already said how it initialized)."""


def _render(model: GaussianModel, viewmats: torch.Tensor, view: int, params: dict[str, torch.Tensor] | None = None,
            sh_degree: int | None = None) -> torch.Tensor:
    """[H, W, 3] CPU render of training view `view` from [C,4,4] `viewmats` (no gradient)."""
    with torch.no_grad():
        images = model.render_views(viewmats[view:view + 1], model.training_views.Ks[view:view + 1], params,
                                    sh_degree)
    return images[0].clamp(0, 1).cpu()


def leave_one_out(coarse: GaussianModel, viewmats: torch.Tensor, config: TrainConfig, left_out: int,
                  should_stop: Callable[[], bool] = lambda: False) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Train the leave-one-out pair of fits for view `left_out` of a finished coarse stage.

    A fit of the other views trains to `loo_snapshot`; then one copy goes on without the view ("unseen") and one
    with it added back ("seen"), to `loo_iters`. The seen copy renders the view `loo_samples` times over the first
    quarter of its continuation (the first render is the pure leave-one-out one).

    Args:
        coarse: the coarse model (its training views, at the full training resolution, are the ones used).
        viewmats: [C,4,4] the coarse stage's poses, frozen here.
        config: the run's config.

    Returns:
        ([S, H, W, 3] renders of the left-out view, name -> [N, ...] unseen - seen final parameters), on the CPU.

    Raises:
        KeyboardInterrupt: `should_stop()` turned true (checked every iteration).
    """
    loo_config, repair = leave_one_out_config(config), config.repair
    views = coarse.training_views
    others = [view for view in range(views.num_views) if view != left_out]
    unseen = LeaveOneOutFit(loo_config, TrainingViews.of(views.scene.subset(others), loo_config, views.device),
                            viewmats[others])
    unseen.train_until(repair.loo_snapshot, should_stop)
    # The seen copy starts as any fit would (so its random stream is a fresh fit's), then takes over the Gaussians.
    seen = LeaveOneOutFit(loo_config, views, viewmats)
    seen.continue_from(unseen)
    span = max((repair.loo_iters - repair.loo_snapshot) // 4, 1)
    sample_at = {repair.loo_snapshot + round(k * span / repair.loo_samples) for k in range(repair.loo_samples)}
    samples = []
    for iteration in sorted(sample_at):
        seen.train_until(iteration, should_stop)
        samples.append(seen.render(left_out))
    seen.train_until(repair.loo_iters, should_stop)
    unseen.train_until(repair.loo_iters, should_stop)
    if seen.model.num_gaussians != unseen.model.num_gaussians:  # densification stopped at the snapshot
        raise RuntimeError("leave-one-out copies diverged in Gaussian count after the snapshot")
    differences = {name: (unseen.model.params[name] - seen.model.params[name]).detach().cpu()
                   for name in NOISY_PARAMETERS}
    return torch.stack(samples), differences


def noise_statistics(differences: list[dict[str, torch.Tensor]]) -> NoiseStatistics:
    """Per-channel mean and std over Gaussians of each model's differences, averaged over the models."""
    mean = {name: torch.stack([d[name].mean(0) for d in differences]).mean(0) for name in NOISY_PARAMETERS}
    std = {name: torch.stack([d[name].std(0) for d in differences]).mean(0) for name in NOISY_PARAMETERS}
    return NoiseStatistics(mean, std)


def perturbed_gaussians(params: dict[str, torch.Tensor], noise: NoiseStatistics, clamp_std: float, dropout: float,
                        generator: torch.Generator) -> dict[str, torch.Tensor]:
    """`params` with 3D noise: each element of the NOISY_PARAMETERS gets N(mean, std) noise with probability
    1 - `dropout`, clamped to mean +- `clamp_std` std except for positions (GaussianObject's add_statistics_noise).
    """
    perturbed = {name: value.detach() for name, value in params.items()}
    for name in NOISY_PARAMETERS:
        value = perturbed[name]
        mean, std = noise.mean[name].to(value), noise.std[name].to(value)
        sample = mean + std * torch.randn(value.shape, generator=generator).to(value)
        if name != "means":
            sample = torch.maximum(torch.minimum(sample, mean + clamp_std * std), mean - clamp_std * std)
        kept = (torch.rand(value.shape, generator=generator) >= dropout).to(value)
        perturbed[name] = value + sample * kept
    return perturbed


def _uniform(bounds: tuple[float, float], generator: torch.Generator) -> float:
    return bounds[0] + (bounds[1] - bounds[0]) * torch.rand(1, generator=generator).item()


def build_pairs(coarse: GaussianModel, viewmats: torch.Tensor, config: TrainConfig,
                should_stop: Callable[[], bool] = lambda: False, log: Callable[[str], None] = print) -> RepairPairs:
    """Leave-one-out and 3D-noise pairs of a finished coarse stage, as `config.repair` sets them.

    Args:
        coarse: the coarse model; its training views (full training resolution) give the targets.
        viewmats: [C,4,4] the coarse stage's poses.
        config: the run's config.
        should_stop: checked every leave-one-out iteration.

    Draws come from a generator seeded with the run's seed, so a resumed run that rebuilds them gets the same.

    Raises:
        KeyboardInterrupt: `should_stop()` turned true.
    """
    repair, targets = config.repair, coarse.training_views.targets
    generator = torch.Generator().manual_seed(config.seed)
    corrupted, pair_targets, kinds, views, differences = [], [], [], [], []
    count = len(viewmats)
    for view in range(count):
        samples, difference = leave_one_out(coarse, viewmats, config, view, should_stop)
        log(f"leave-one-out model {view + 1}/{count}: {len(samples)} renders of view {view}")
        corrupted += list(samples)
        pair_targets += [targets[view].cpu()] * len(samples)
        kinds += [LEAVE_ONE_OUT] * len(samples)
        views += [view] * len(samples)
        differences.append(difference)
    noise = noise_statistics(differences)
    for view in range(count):
        for _ in range(repair.noise_renders):
            params = perturbed_gaussians(coarse.params, noise, _uniform(repair.noise_clamp_std, generator),
                                         _uniform(repair.noise_dropout, generator), generator)
            corrupted.append(_render(coarse, viewmats, view, params))
            pair_targets.append(targets[view].cpu())
            kinds.append(NOISE)
            views.append(view)
    return RepairPairs(torch.stack(corrupted), torch.stack(pair_targets), kinds, views, noise)
