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

from warpbags.configs.train import TrainConfig
from warpbags.files import atomic_output

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


def _render(trainer, view: int, params: dict[str, torch.Tensor] | None = None) -> torch.Tensor:
    """[H, W, 3] CPU render of `trainer`'s view `view` at its current pose (no gradient)."""
    with torch.no_grad():
        images = trainer.render_views(trainer.current_viewmats()[view:view + 1], trainer.Ks[view:view + 1], params)
    return images[0].clamp(0, 1).cpu()


def _train_until(trainer, iteration: int, should_stop: Callable[[], bool]) -> None:
    while trainer.iteration < iteration:
        if should_stop():
            raise KeyboardInterrupt
        trainer.train_step()


def leave_one_out(trainer, left_out: int, should_stop: Callable[[], bool] = lambda: False
                  ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Train the leave-one-out pair of models for view `left_out` of `trainer` (a finished coarse stage).

    A model of the other views trains to `loo_snapshot`; then one copy goes on without the view ("unseen") and
    one with it added back ("seen"), to `loo_iters`. The seen copy renders the view `loo_samples` times over the
    first quarter of its continuation (the first render is the pure leave-one-out one).

    Returns:
        ([S, H, W, 3] renders of the left-out view, name -> [N, ...] unseen - seen final parameters), on the CPU.

    Raises:
        KeyboardInterrupt: `should_stop()` turned true (checked every iteration).
    """
    config = leave_one_out_config(trainer.config)
    repair = trainer.config.repair
    viewmats = trainer.current_viewmats()
    others = [view for view in range(trainer.num_cameras) if view != left_out]
    folder = trainer.out_dir / "repair" / f"loo_{left_out}"  # never written: these trainers only train_step
    make = lambda scene, poses: type(trainer)(scene, config, folder, device=str(trainer.device),  # noqa: E731
                                              viewmats_init=poses, log=lambda message: None)
    unseen = make(trainer.scene.subset(others), viewmats[others])
    _train_until(unseen, repair.loo_snapshot, should_stop)
    seen = make(trainer.scene, viewmats)
    seen.continue_from(unseen)
    span = max((repair.loo_iters - repair.loo_snapshot) // 4, 1)
    sample_at = {repair.loo_snapshot + round(k * span / repair.loo_samples) for k in range(repair.loo_samples)}
    samples = []
    for iteration in sorted(sample_at):
        _train_until(seen, iteration, should_stop)
        samples.append(_render(seen, left_out))
    _train_until(seen, repair.loo_iters, should_stop)
    _train_until(unseen, repair.loo_iters, should_stop)
    if len(seen.params["means"]) != len(unseen.params["means"]):  # densification stopped at the snapshot
        raise RuntimeError("leave-one-out copies diverged in Gaussian count after the snapshot")
    differences = {name: (unseen.params[name] - seen.params[name]).detach().cpu() for name in NOISY_PARAMETERS}
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


def build_pairs(trainer, log: Callable[[str], None] = print) -> RepairPairs:
    """Leave-one-out and 3D-noise pairs for `trainer` (a finished coarse stage), as `RepairConfig` sets them.

    Draws come from a generator seeded with the run's seed, so a resumed run that rebuilds them gets the same.

    Raises:
        KeyboardInterrupt: Ctrl-C was pressed (`trainer.stop_requested`).
    """
    repair = trainer.config.repair
    generator = torch.Generator().manual_seed(trainer.config.seed)
    should_stop = lambda: trainer.stop_requested  # noqa: E731
    corrupted, targets, kinds, views, differences = [], [], [], [], []
    for view in range(trainer.num_cameras):
        samples, difference = leave_one_out(trainer, view, should_stop)
        log(f"leave-one-out model {view + 1}/{trainer.num_cameras}: {len(samples)} renders of view {view}")
        corrupted += list(samples)
        targets += [trainer.targets[view].cpu()] * len(samples)
        kinds += [LEAVE_ONE_OUT] * len(samples)
        views += [view] * len(samples)
        differences.append(difference)
    noise = noise_statistics(differences)
    for view in range(trainer.num_cameras):
        for _ in range(repair.noise_renders):
            params = perturbed_gaussians(trainer.params, noise, _uniform(repair.noise_clamp_std, generator),
                                         _uniform(repair.noise_dropout, generator), generator)
            corrupted.append(_render(trainer, view, params))
            targets.append(trainer.targets[view].cpu())
            kinds.append(NOISE)
            views.append(view)
    return RepairPairs(torch.stack(corrupted), torch.stack(targets), kinds, views, noise)
