"""`Schedule`: what a training iteration does, as a function of the iteration and the config alone.

Rounds (fresh Gaussians each), the pyramid level of each round, the SH degree, the coarse-to-fine blur, the
windows of the silhouette and depth terms, the pose window and both learning-rate schedules all follow from
(`TrainConfig`, iteration). `Schedule.at(iteration)` gathers them into a `StepSettings` that the Gaussian model
(`warpbags.model`) and the camera optimizer are given for one step; the trainer and the repair stage's
leave-one-out fits run the same schedule.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

from warpbags.configs.train import TrainConfig


def exponential_lr(initial: float, final: float, fraction: float) -> float:
    """Log-linear interpolation from `initial` (fraction 0) to `final` (fraction 1), clamped to [0, 1]."""
    fraction = min(max(fraction, 0.0), 1.0)
    return math.exp((1 - fraction) * math.log(initial) + fraction * math.log(final))


@dataclass(frozen=True)
class StepSettings:
    """Everything one iteration needs from the schedule.

    Attributes:
        round_iteration: iterations done in the current round (Gaussian schedules restart with each round).
        sh_degree: SH degree rendered.
        blur_sigma: coarse-to-fine blur of renders and targets, pixels (0 = none).
        silhouette: the mask-distance and chamfer terms are on.
        depth: the depth term is on.
        pose_active: the cameras rendered take an Adam step.
        pose_solve: after the Gaussians' step, every camera is solved by L-BFGS against them
            (`camera.lbfgs_from_round`; then `pose_active` is False).
        gaussian_lr_fraction: position-lr schedule position in [0, 1] (exponential from `lr.means_init` to
            `lr.means_final`).
        pose_lr: the camera optimizer's rotation learning rate.
        orbit_free: the object-centric orbit rows are optimized (`camera.orbit_from_round`).
        pose_anchor: weight of the pull of the rendered cameras' corrections towards where the round started
            (`camera.round_anchor` from the second round on and in the repair stage, where it pulls towards the
            coarse stage's final poses).
        pose_average: the poses after this step join the average that becomes the final poses
            (`camera.average_share`).
        densify: the densification strategy may add Gaussians or reset opacities after this step; not at a coarse
            round's last iteration, after which no step trains what they would add: the last round's model is
            saved, an earlier one's scored (the turn search's worst-fit camera) and replaced by fresh Gaussians.
    """

    round_iteration: int
    sh_degree: int
    blur_sigma: float
    silhouette: bool
    depth: bool
    pose_active: bool
    pose_solve: bool
    gaussian_lr_fraction: float
    pose_lr: float
    orbit_free: bool
    pose_anchor: float
    pose_average: bool
    densify: bool = True


class Schedule:
    """The iteration schedule of one `TrainConfig`: coarse rounds, then the repair stage."""

    def __init__(self, config: TrainConfig):
        self.config = config
        # Rounds re-carve the hull with improved poses; with frozen poses (the baseline) they would only throw
        # trained Gaussians away, so the baseline trains one round with the whole budget.
        self.rounds = config.rounds if config.pose_opt else 1
        # Every configured round runs, their lengths differ by at most one iteration, and the longer ones come last
        # (the last round's Gaussians are the result): the last iters % rounds rounds take one iteration more.
        short, longer = divmod(config.iters, self.rounds)
        self.round_starts = [k * short + max(0, k - (self.rounds - longer)) for k in range(self.rounds)]

    def round_iteration(self, iteration: int) -> int:
        """The iteration within its coarse round; in the repair stage, within the repair stage (nothing there
        restarts: it neither densifies nor steps the SH degree or the blur)."""
        if iteration >= self.config.iters:
            return iteration - self.config.iters
        return iteration - self.round_starts[self.round_index(iteration)]

    def starts_round(self, iteration: int) -> bool:
        """True at the first iteration of every coarse round after the first (fresh Gaussians)."""
        return iteration > 0 and not self.in_repair(iteration) and self.round_iteration(iteration) == 0

    def in_repair(self, iteration: int) -> bool:
        return self.config.repair.iters > 0 and iteration >= self.config.iters

    def pyramid_level(self, iteration: int) -> int:
        """The round's level (0: full resolution): with L levels the last round trains at full resolution, the one
        before at half of it, and so on for L rounds; earlier rounds stay at the coarsest level, 1/2^(L-1). The
        repair stage is at full resolution."""
        if self.in_repair(iteration):
            return 0
        return min(self.config.pyramid_levels - 1, self.rounds - 1 - self.round_index(iteration))

    def sh_degree(self, iteration: int) -> int:
        if self.in_repair(iteration):
            return self.config.sh_degree
        return min(self.config.sh_degree, self.round_iteration(iteration) // max(self.config.sh_degree_every, 1))

    def final_sh_degree(self) -> int:
        """The SH degree the saved model was last trained at: the repair stage's (the configured one), else the one
        the last coarse round's last iteration reaches (a degree every `sh_degree_every` iterations of the round)."""
        return self.sh_degree(self.config.total_iters - 1)

    def blur_sigma(self, iteration: int) -> float:
        """Coarse-to-fine blur (pixels)."""
        config = self.config
        if config.blur_until <= 0 or self.in_repair(iteration):
            return 0.0
        return config.blur_sigma_px * max(0.0, 1.0 - self.round_iteration(iteration) / config.blur_until)

    def round_index(self, iteration: int) -> int:
        """The 0-based coarse round of `iteration` (the repair stage counts as the last round)."""
        return bisect.bisect_right(self.round_starts, iteration) - 1

    def round_end(self, iteration: int) -> int:
        """The first iteration after the coarse round of `iteration` (the coarse stage's end for the repair stage)."""
        next_round = self.round_index(iteration) + 1
        return self.round_starts[next_round] if next_round < self.rounds else self.config.iters

    def round_length(self, round_index: int) -> int:
        """The iterations of coarse round `round_index`."""
        round_start = self.round_starts[round_index]
        return self.round_end(round_start) - round_start

    def orbit_free(self, iteration: int) -> bool:
        return self.round_index(iteration) >= self.config.camera.orbit_from_round

    def pose_window(self, iteration: int) -> tuple[int, int]:
        """[start, end) iterations of the current round in which poses are updated (`_pose_window_offsets`; no
        earlier than `pose_opt_start`)."""
        round_index = self.round_index(iteration)
        round_start = self.round_starts[round_index]
        first, stop = self._pose_window_offsets(round_index)
        return max(round_start + first, self.config.pose_opt_start), min(round_start + stop, self.config.iters)

    def rounds_without_pose_window(self) -> list[int]:
        """The coarse rounds whose pose window, as shares of the round, rounds to no iteration (whatever
        `pose_opt_start` says): their poses hold still however the run is started."""
        if not self.config.pose_opt:
            return []
        empty = []
        for index in range(self.rounds):
            first, stop = self._pose_window_offsets(index)
            if first >= stop:
                empty.append(index)
        return empty

    def _pose_window_offsets(self, round_index: int) -> tuple[int, int]:
        """[first, stop) of coarse round `round_index`'s pose window, in iterations from the round's start: the
        round's entry of `pose_round_windows`, else `pose_round_window`, as shares of the round's own length, so
        that rounds of unequal length each have theirs."""
        length = max(self.round_length(round_index), 1)
        windows = self.config.pose_round_windows or (self.config.pose_round_window,)
        window_start, window_end = windows[min(round_index, len(windows) - 1)]
        return share_of(window_start, length), share_of(window_end, length)

    def poses_move(self, iteration: int) -> bool:
        """Poses are updated (by Adam steps or L-BFGS solves, `at`) from `pose_opt_start` on, inside each coarse
        round's pose window (and in the repair stage)."""
        if not self.config.pose_opt or iteration < self.config.pose_opt_start:
            return False
        start, end = self.pose_window(iteration)
        return self.in_repair(iteration) or start <= iteration < end

    def averages_poses(self, iteration: int) -> bool:
        """The poses after this coarse iteration join the average that becomes the final poses: the last
        `camera.average_share` of the last round's pose window, when poses are optimized."""
        share = self.config.camera.average_share
        if share <= 0 or self.in_repair(iteration) or self.round_index(iteration) < self.rounds - 1:
            return False
        start, end = self.pose_window(iteration)
        return self.poses_move(iteration) and iteration >= end - share_of(share, end - start)

    def solves_poses(self, iteration: int) -> bool:
        """Poses move by L-BFGS solves instead of Adam steps in this iteration's round (`camera.lbfgs_from_round`;
        coarse rounds only)."""
        first = self.config.camera.lbfgs_from_round
        return first is not None and not self.in_repair(iteration) and self.round_index(iteration) >= first

    def at(self, iteration: int) -> StepSettings:
        config, round_iteration, in_repair = self.config, self.round_iteration(iteration), self.in_repair(iteration)
        # GaussianObject's repair keeps the final position lr; the poses keep their final lr. The pose lr decays
        # within each round's pose window (a warm restart per round: each round is a fresh coarse-to-fine fit).
        # The position lr decays over the round's own length: rounds of unequal length all end at its final value.
        this_round_length = self.round_length(self.round_index(iteration))
        gaussian_fraction = 1.0 if in_repair else round_iteration / max(this_round_length - 1, 1)
        pose_start, pose_end = self.pose_window(iteration)
        pose_fraction = 1.0 if in_repair else (iteration - pose_start) / max(pose_end - pose_start - 1, 1)
        # a linear ramp over the first `lr.pose_warmup` steps of each window and of the repair stage, from where the
        # poses first move in it (`pose_opt_start` may come later): Adam's moments start at zero there (each round
        # rebases the cameras, and so does the coarse stage's end)
        warmup_steps = config.lr.pose_warmup
        window_start = max(config.iters if in_repair else pose_start, config.pose_opt_start)
        warmup = 1.0 if warmup_steps <= 0 else min(1.0, max(iteration - window_start + 1, 1) / warmup_steps)
        # the repair stage's real-view loss is the coarse stage's as it ended (for the fixed-pose baseline too, so
        # the two stay comparable): the silhouette terms, which hold the poses that keep moving, stay where they were
        # on; the depth term, which ends early in each round, stays off
        silhouette_iteration = self.round_iteration(config.iters - 1) if in_repair else round_iteration
        poses_move, solves = self.poses_move(iteration), self.solves_poses(iteration)
        return StepSettings(
            round_iteration=round_iteration,
            sh_degree=self.sh_degree(iteration), blur_sigma=self.blur_sigma(iteration),
            silhouette=config.silhouette_until <= 0 or silhouette_iteration < config.silhouette_until,
            depth=not in_repair and round_iteration < config.depth_until and config.lambda_depth > 0,
            pose_active=poses_move and not solves,
            # the window's last iteration solves too: a window shorter than `lbfgs_every` would otherwise never
            pose_solve=poses_move and solves and ((iteration + 1) % config.camera.lbfgs_every == 0
                                                  or iteration == pose_end - 1),
            gaussian_lr_fraction=gaussian_fraction,
            pose_lr=exponential_lr(config.lr.pose, config.lr.pose_final, pose_fraction) * warmup,
            orbit_free=self.orbit_free(iteration),
            pose_anchor=config.camera.round_anchor if in_repair or self.round_index(iteration) > 0 else 0.0,
            pose_average=self.averages_poses(iteration),
            densify=iteration != self.round_end(iteration) - 1,
        )


def share_of(share: float, length: int) -> int:
    """The iterations that `share` of `length` spans, rounded up: 0.55 of 100 is 55 (its float product,
    55.00000000000001, would round up to 56)."""
    return math.ceil(round(share * length, 9))
