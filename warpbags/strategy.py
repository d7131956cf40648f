"""Adaptive density control (3DGS): clone, split, prune, opacity reset, kept apart from rendering.

The strategy sees a dict of Gaussian parameters (``torch.nn.Parameter``, 3DGS parameterization: log scales,
logit opacities) and the one Adam optimizer holding them, one parameter group per name (``group["name"]``).
Adding or removing Gaussians replaces the parameters and carries Adam's moments along (zeros for new rows).
"""

from __future__ import annotations

import math

import torch

from warpbags.configs.train import DensifyConfig
from warpbags.errors import WarpbagsError
from warpbags.wrapper import mean_neighbour_distances


def replace_rows(
    params: dict[str, torch.nn.Parameter], optimizer: torch.optim.Optimizer, select: torch.Tensor, append: dict[str, torch.Tensor] | None = None
) -> None:
    """Keep the rows `select` ([N] bool) of every parameter and append rows `append[name]`, updating Adam state.

    Args:
        params: name -> [N, ...] parameters; replaced in place in the dict.
        optimizer: Adam whose groups each hold one parameter and carry its name in ``group["name"]``.
        select: [N] bool rows to keep.
        append: name -> [M, ...] new rows (their Adam moments start at zero), or None.
    """
    for group in optimizer.param_groups:
        name = group["name"]
        old = group["params"][0]
        extra = None if append is None else append[name].to(old)
        new = torch.nn.Parameter(old.detach()[select] if extra is None else torch.cat([old.detach()[select], extra]))
        state = optimizer.state.pop(old, None)
        if state is not None:
            for key in ("exp_avg", "exp_avg_sq"):
                kept = state[key][select]
                state[key] = kept if extra is None else torch.cat([kept, torch.zeros_like(extra)])
            optimizer.state[new] = state
        group["params"][0] = new
        params[name] = new


def quats_to_rotmats(quats: torch.Tensor) -> torch.Tensor:
    """[N, 4] wxyz quaternions (any norm) -> [N, 3, 3] rotation matrices."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)


class DensifyStrategy:
    """3DGS's densification: accumulate view-space gradient norms, then clone / split / prune / reset.

    Usage per iteration: render with ``meta["means2d"].retain_grad()``, backward, :meth:`accumulate`,
    ``optimizer.step()``, then :meth:`step` (which may change the number of Gaussians).

    Args:
        config: thresholds and schedule.
        scene_extent: scene size the percentages refer to (1.1 x camera-centre radius, as 3DGS).
        white_background: the opacity reset and the floater removal (where on) run once more at `config.start`, as
            3DGS and GaussianObject do on a white background.
    """

    def __init__(self, config: DensifyConfig, scene_extent: float, white_background: bool = False):
        self.config = config
        self.scene_extent = scene_extent
        self.white_background = white_background
        self.grad_sum: torch.Tensor | None = None  # [N] accumulated NDC gradient norms
        self.grad_count: torch.Tensor | None = None  # [N] how many times each Gaussian was visible

    def state_dict(self) -> dict:
        return {"grad_sum": self.grad_sum, "grad_count": self.grad_count}

    def load_state_dict(self, state: dict) -> None:
        self.grad_sum, self.grad_count = state["grad_sum"], state["grad_count"]

    def _reset_stats(self, count: int, device: torch.device) -> None:
        self.grad_sum = torch.zeros(count, device=device)
        self.grad_count = torch.zeros(count, device=device)

    @torch.no_grad()
    def accumulate(self, iteration: int, meta: dict) -> None:
        """Add this step's view-space positional gradient norms.

        Pixel gradients are scaled to NDC (x W/2, y H/2) and by the number of cameras in the batch, so the
        threshold means what it means in 3DGS (one view per step) whatever the batch.

        Raises:
            WarpbagsError: ``meta["means2d"].grad`` is None (its gradient was not retained before backward).
        """
        if iteration >= self.config.stop:
            return
        means2d, radii = meta["means2d"], meta["radii"]  # [C,N,2], [C,N]
        if means2d.grad is None:  # densifying on no statistics would silently stop adding Gaussians (gsplat asserts)
            raise WarpbagsError("densification needs the gradient of meta['means2d']: call "
                                "meta['means2d'].retain_grad() before backward()")
        count = means2d.shape[1]
        # Every row change here keeps the statistics in step; a checkpoint of an earlier version saved after a
        # floater removal holds them at the length before it, so they restart.
        if self.grad_sum is None or len(self.grad_sum) != count:
            self._reset_stats(count, means2d.device)
        # The loss is a mean over the batch's cameras, so each camera's gradient is 1/C of what it would be alone:
        # scaled back by C (as gsplat does), the threshold means the same for any number of views per step.
        grads = means2d.grad.clone() * means2d.shape[0]
        grads[..., 0] *= meta["width"] / 2.0
        grads[..., 1] *= meta["height"] / 2.0
        visible = radii > 0
        self.grad_sum += (grads.norm(dim=-1) * visible).sum(0)
        self.grad_count += visible.sum(0)

    @torch.no_grad()
    def step(self, iteration: int, params: dict[str, torch.nn.Parameter], optimizer: torch.optim.Optimizer,
             generator: torch.Generator, grows: bool = True) -> dict[str, int]:
        """Run the scheduled operations after the optimizer step of `iteration` (1-based count of steps done).
        With `grows` False (no step follows to train them: the schedule's `StepSettings.densify`) the densification
        and the opacity reset are skipped, the floater removal is not.

        Returns:
            counts of cloned, split and pruned Gaussians (empty when nothing was scheduled).
        """
        config = self.config
        report: dict[str, int] = {}
        if (grows and config.start <= iteration < config.stop and iteration % config.every == 0
                and self.grad_sum is not None):
            report = self._densify_and_prune(params, optimizer, generator)
            self._reset_stats(len(params["means"]), params["means"].device)
        at_white_start = self.white_background and iteration == config.start
        if (config.floater_every and (iteration % config.floater_every == 0 or at_white_start)
                and iteration < config.stop):
            removed = self._remove_floaters(params, optimizer)
            if removed:
                report["floaters"] = removed
        if (grows and config.opacity_reset_every and (iteration % config.opacity_reset_every == 0 or at_white_start)
                and iteration < config.stop):
            self._reset_opacities(params, optimizer)
            report["opacity_reset"] = 1
        return report

    def _densify_and_prune(self, params, optimizer, generator) -> dict[str, int]:
        config = self.config
        count = len(params["means"])
        average = self.grad_sum / self.grad_count.clamp_min(1)
        large_grad = average >= config.grad_threshold
        max_scale = params["scales"].exp().max(dim=1).values
        small = max_scale <= config.percent_dense * self.scene_extent
        clone, split = large_grad & small, large_grad & ~small
        if config.max_gaussians:
            budget = max(config.max_gaussians - count, 0)
            # Favour the largest gradients when the budget is short (a split adds one net Gaussian, as a clone).
            candidates = torch.nonzero(clone | split).squeeze(1)
            if len(candidates) > budget:
                keep = candidates[average[candidates].argsort(descending=True)[:budget]]
                chosen = torch.zeros(count, dtype=torch.bool, device=average.device)
                chosen[keep] = True
                clone, split = clone & chosen, split & chosen
        new_rows = {name: param.detach()[clone] for name, param in params.items()}
        # Split: two samples from each large Gaussian, scales / 1.6, originals removed.
        stds = params["scales"].exp()[split].repeat(2, 1)
        samples = torch.randn(stds.shape, generator=generator).to(stds) * stds
        rotations = quats_to_rotmats(params["quats"][split]).repeat(2, 1, 1)
        split_rows = {name: param.detach()[split].repeat(2, *([1] * (param.dim() - 1))) for name, param in params.items()}
        split_rows["means"] = split_rows["means"] + (rotations @ samples[..., None])[..., 0]
        split_rows["scales"] = torch.log(stds / 1.6)
        append = {name: torch.cat([new_rows[name], split_rows[name]]) for name in params}
        replace_rows(params, optimizer, ~split, append)
        # Prune transparent and oversized Gaussians.
        opacities = torch.sigmoid(params["opacities"])
        max_scale = params["scales"].exp().max(dim=1).values
        prune = (opacities < config.prune_opacity) | (max_scale > config.prune_scale * self.scene_extent)
        if prune.all():  # never remove every Gaussian
            prune[opacities.argmax()] = False
        replace_rows(params, optimizer, ~prune)
        return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": int(prune.sum())}

    def _remove_floaters(self, params, optimizer) -> int:
        """Remove statistical outliers: Gaussians whose mean distance to their K = sqrt(N) nearest neighbours is
        more than `floater_std_ratio` standard deviations above the average (GaussianObject's kNN floater
        removal, with Open3D's outlier rule). Returns how many were removed."""
        means = params["means"].detach()
        count = len(means)
        k = int(math.isqrt(count))
        if k < 2:
            return 0
        mean_distance = mean_neighbour_distances(means, k)
        floaters = mean_distance > mean_distance.mean() + self.config.floater_std_ratio * mean_distance.std()
        if floaters.any():
            replace_rows(params, optimizer, ~floaters)
            # The survivors keep their statistics (as gsplat's `remove`): left at the old length, `accumulate` would
            # restart them all and the interval's densification would see only the steps after the removal.
            if self.grad_sum is not None and len(self.grad_sum) == count:
                self.grad_sum, self.grad_count = self.grad_sum[~floaters], self.grad_count[~floaters]
        return int(floaters.sum())

    def _reset_opacities(self, params, optimizer) -> None:
        """Clamp opacities to at most 0.01 and zero their Adam moments (3DGS's `reset_opacity`)."""
        ceiling = math.log(0.01 / 0.99)
        opacities = params["opacities"]
        opacities.data.clamp_(max=ceiling)
        state = optimizer.state.get(opacities)
        if state:
            state["exp_avg"].zero_()
            state["exp_avg_sq"].zero_()
