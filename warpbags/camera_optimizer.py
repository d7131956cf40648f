"""`CameraOptimizer`: the one home of the learnable camera corrections (nerfstudio's CameraOptimizer, CamP's deltas).

It holds the per-camera parameters, the gauge, the optional CamP preconditioner, the Adam optimizer with its two
groups (rotation, translation) and its learning rate, and turns the parameters into corrected world-to-camera
matrices: `cameras(views)` (`forward`; a `torch.nn.Module` keeps `apply` for its own meaning). The trainer and
evaluation's test-pose refinement go through it; export writes the poses it left.

Parameterizations (`kernels/pose.py` has the maths, one Warp kernel each):
    "camera"  se(3) twist [w, v] composed on the left of world-to-camera: a rotation about the camera centre (BARF).
    "object"  [w, u, s]: rotation about the object centre, image-plane shift of the object (u, in focal lengths)
              and log depth s (CamP's object-centric deltas). A rotation about the camera centre and a sideways
              shift move a small distant object's image almost alike; here the strong image motion is u alone.

Preconditioning (CamP, Park et al. 2023): the latent parameters z are mapped to the real ones by a fixed per-camera
P = (M + diag(max(1e-8, r diag M)))^(-1/2), M = J^T J / n, J the Jacobian of the object's projected points (pixels
divided by max(W, H)) with respect to the 6 parameters at zero. A unit step of z then moves the image by about the
same amount in every direction, so one learning rate fits rotation and translation alike, and directions that
barely move the image (a viewpoint turn about a far object) are not starved by Adam.

Orbit freezing (object parameterization): `set_orbit_free(False)` holds wx, wy (the turn about the object centre
that keeps the object where it is in the image) at zero. Adam's per-coordinate steps still move the latent along
directions the frozen rows hide, so releasing the orbit first folds the current corrections into the base poses and
restarts the latents and their moments at zero: the estimate does not jump.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch

from warpbags.cameras import camera_centers, mean_viewmats, project_points
from warpbags.configs.train import CameraConfig
from warpbags.errors import WarpbagsError
from warpbags.wrapper import apply_object_deltas, apply_pose_deltas

PARAMETERIZATIONS = ("camera", "object")
ORBIT_ROWS = (0, 1)  # wx, wy of the object parameterization


def corrected_viewmats(parameterization: str, viewmats: torch.Tensor, params: torch.Tensor,
                       object_centers: torch.Tensor | None = None) -> torch.Tensor:
    """[C, 4, 4] `viewmats` corrected by [C, 6] `params` of the given parameterization ("camera" or "object")."""
    if parameterization == "camera":
        return apply_pose_deltas(viewmats, params)
    if parameterization == "object":
        if object_centers is None:
            raise ValueError("the object parameterization needs object_centers")
        return apply_object_deltas(viewmats, params, object_centers)
    raise WarpbagsError(f"camera parameterization must be one of {', '.join(PARAMETERIZATIONS)}, got {parameterization!r}")


def preconditioner(parameterization: str, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                   points: torch.Tensor, object_centers: torch.Tensor, regularization: float,
                   step: float = 1e-4) -> torch.Tensor:
    """CamP's P = (M + diag(max(1e-8, r diag M)))^(-1/2) per camera, M = J^T J / n.

    J is the Jacobian of the projected `points` (in image sizes) with respect to the 6 parameters at zero, by central
    differences of the real pose transform in float64 (exact to ~step^2). Points behind a camera are left out.

    Returns:
        [C, 6, 6] symmetric positive-definite matrices (real params = P @ latent).
    """
    cams = viewmats.shape[0]
    viewmats, Ks, points = viewmats.double(), Ks.double(), points.double()
    centers = object_centers.double()
    scale = float(max(width, height))
    columns = []
    for k in range(6):
        offset = torch.zeros(cams, 6, dtype=torch.float64, device=viewmats.device)
        offset[:, k] = step
        plus, _ = project_points(corrected_viewmats(parameterization, viewmats, offset, centers), Ks, points)
        minus, _ = project_points(corrected_viewmats(parameterization, viewmats, -offset, centers), Ks, points)
        columns.append((plus - minus) / (2 * step * scale))  # [C, P, 2]
    jacobian = torch.stack(columns, dim=-1)  # [C, P, 2, 6]
    _, depths = project_points(viewmats, Ks, points)
    visible = (depths > 1e-3).double()[..., None, None]
    jacobian = (jacobian * visible).reshape(cams, -1, 6)
    count = (visible.reshape(cams, -1).sum(-1) * 2).clamp_min(1.0)
    moments = jacobian.transpose(1, 2) @ jacobian / count[:, None, None]  # [C, 6, 6]
    diagonal = torch.diagonal(moments, dim1=1, dim2=2)
    damped = moments + torch.diag_embed((regularization * diagonal).clamp_min(1e-8))
    eigenvalues, eigenvectors = torch.linalg.eigh(damped)
    return (eigenvectors * eigenvalues.rsqrt()[:, None, :]) @ eigenvectors.transpose(1, 2)


@dataclass(frozen=True)
class CameraOptimizerSettings:
    """What a CameraOptimizer needs beyond the cameras (filled from `configs.train.CameraConfig` and the lr group).

    Attributes:
        parameterization: "camera" or "object".
        precondition: use CamP's preconditioner (computed once, at construction).
        precondition_reg: its damping r.
        fix_first_camera: gauge; camera 0 keeps its starting pose.
        lr: rotation-group learning rate at the start of a schedule; translation gets lr * translation_scale.
        translation_scale: translation lr relative to rotation.
    """

    parameterization: str = "object"
    precondition: bool = True
    precondition_reg: float = 0.1
    fix_first_camera: bool = False
    lr: float = 1e-2
    translation_scale: float = 1.0

    @classmethod
    def from_config(cls, camera: CameraConfig, lr: float = 1e-2, translation_scale: float = 1.0) -> CameraOptimizerSettings:
        """The settings of a training config's `camera` group, with the given learning rate."""
        return cls(parameterization=camera.parameterization, precondition=camera.precondition,
                   precondition_reg=camera.precondition_reg, fix_first_camera=camera.fix_first_camera, lr=lr,
                   translation_scale=translation_scale)


# The running sums of `CameraOptimizer.accumulate_average`: rotations [C, 3, 3], centres [C, 3], estimates [].
AVERAGE_BUFFERS = ("average_rotation_sums", "average_center_sums", "average_count")


class CameraOptimizer(torch.nn.Module):
    """Per-camera pose corrections of C cameras, their gauge, preconditioner and Adam optimizer.

    Args:
        base_viewmats: [C, 4, 4] world-to-camera poses the corrections are relative to: the starting poses, until
            `rebase`, `reset_to`, `apply_average` or `turn_about_object` moves them (the buffer of the same name).
        settings: parameterization, preconditioning, gauge and learning rate.
        object_center: [3] world point the object-centric parameterization turns about.
        Ks, width, height, points: cameras and [P, 3] object points for the preconditioner (needed only with
            `settings.precondition`).
    """

    def __init__(self, base_viewmats: torch.Tensor, settings: CameraOptimizerSettings, object_center: torch.Tensor,
                 Ks: torch.Tensor | None = None, width: int = 0, height: int = 0, points: torch.Tensor | None = None):
        super().__init__()
        self.settings = settings
        cams, options = base_viewmats.shape[0], dict(dtype=base_viewmats.dtype, device=base_viewmats.device)
        self.register_buffer("base_viewmats", base_viewmats.detach().clone())
        self.register_buffer("object_centers", object_center.to(**options).expand(cams, 3).contiguous())
        gauge = torch.ones(cams, 1, **options)
        if settings.fix_first_camera:
            gauge[0] = 0.0
        self.register_buffer("gauge", gauge)
        if settings.precondition:
            if points is None or Ks is None:
                raise ValueError("preconditioning needs Ks and object points")
            matrix = preconditioner(settings.parameterization, base_viewmats.detach(), Ks.detach(), width, height,
                                    points.detach(), self.object_centers, settings.precondition_reg)
        else:
            matrix = torch.eye(6, dtype=torch.float64).expand(cams, 6, 6)
        self.register_buffer("preconditioner", matrix.to(**options).contiguous())
        self.register_buffer("free_rows", torch.ones(6, **options))  # 0 where a parameter is held (orbit freezing)
        # Sums of the estimates averaged into the final poses (`accumulate_average`), in float64: a checkpoint keeps
        # them, and so does the state a searched round restarts from.
        sums = dict(dtype=torch.float64, device=base_viewmats.device)
        for name, shape in zip(AVERAGE_BUFFERS, ((cams, 3, 3), (cams, 3), ())):
            self.register_buffer(name, torch.zeros(shape, **sums))
        # Rotation and translation latents: two Adam groups, each created once (resume loads into them).
        self.rotations = torch.nn.Parameter(torch.zeros(cams, 3, **options))
        self.translations = torch.nn.Parameter(torch.zeros(cams, 3, **options))
        self.optimizer = torch.optim.Adam([
            {"params": [self.rotations], "lr": settings.lr, "name": "rotation"},
            {"params": [self.translations], "lr": settings.lr * settings.translation_scale, "name": "translation"},
        ])

    @property
    def num_cameras(self) -> int:
        return self.base_viewmats.shape[0]

    def movable_cameras(self) -> list[int]:
        """The cameras the optimizer may move: all but a gauge camera held at its given pose."""
        return [camera for camera in range(self.num_cameras) if self.gauge[camera, 0] != 0]

    def params(self) -> torch.Tensor:
        """[C, 6] the real parameters, P @ latent, zero for the gauge camera and in held rows."""
        latent = torch.cat([self.rotations, self.translations], dim=1)
        return (self.preconditioner @ latent[..., None])[..., 0] * self.gauge * self.free_rows

    def forward(self, views: torch.Tensor | None = None) -> torch.Tensor:
        """[B, 4, 4] corrected world-to-camera matrices of cameras `views` ([B] long, default all); differentiable."""
        params = self.params()
        if views is None:
            return corrected_viewmats(self.settings.parameterization, self.base_viewmats, params, self.object_centers)
        return corrected_viewmats(self.settings.parameterization, self.base_viewmats[views].contiguous(),
                                  params[views].contiguous(), self.object_centers[views].contiguous())

    def viewmats(self) -> torch.Tensor:
        """[C, 4, 4] the current estimate of every camera, without a graph."""
        with torch.no_grad():
            return self()

    def poses(self, views: torch.Tensor, differentiable: bool) -> torch.Tensor:
        """[B, 4, 4] the current poses of cameras `views` ([B] long), differentiable in the camera parameters only
        when `differentiable` (a step whose poses hold still renders them without a graph)."""
        return self(views) if differentiable else self.viewmats()[views]

    @property
    def orbit_free(self) -> bool:
        return bool(self.free_rows[ORBIT_ROWS[0]] > 0)

    def set_orbit_free(self, free: bool) -> None:
        """Optimize the orbit rows (wx, wy) or hold them at zero (object parameterization only). Releasing them
        rebases first (see the module docstring)."""
        if free == self.orbit_free:
            return
        if self.settings.parameterization != "object":
            raise WarpbagsError("orbit freezing needs the object parameterization")
        if free:
            self.rebase()
        with torch.no_grad():
            self.free_rows[list(ORBIT_ROWS)] = 1.0 if free else 0.0

    def rebase(self) -> None:
        """Fold the current corrections into the base poses; latents and Adam moments restart at zero."""
        with torch.no_grad():
            self.reset_to(self())

    def reset_to(self, viewmats: torch.Tensor) -> None:
        """Make [C, 4, 4] `viewmats` the base poses, with no corrections: latents and Adam moments restart at zero."""
        with torch.no_grad():
            self.base_viewmats.copy_(viewmats.to(self.base_viewmats))
            self.rotations.zero_()
            self.translations.zero_()
        self.reset_moments()

    def accumulate_average(self) -> None:
        """Add every camera's current estimate to the average that `apply_average` makes the poses."""
        with torch.no_grad():
            viewmats = self().double()
            self.average_rotation_sums += viewmats[:, :3, :3]
            self.average_center_sums += camera_centers(viewmats)
            self.average_count += 1

    def apply_average(self) -> None:
        """Make the mean of the accumulated estimates the cameras' poses (`reset_to`: no corrections left) and empty
        the average; nothing when no estimate was accumulated."""
        count = int(self.average_count.item())
        if count == 0:
            return
        mean = mean_viewmats(self.average_rotation_sums, self.average_center_sums, count).to(self.base_viewmats)
        held = self.gauge[:, 0] == 0
        mean[held] = self.base_viewmats[held]  # a gauge camera keeps its given pose to the bit
        self.reset_to(mean)
        with torch.no_grad():
            for name in AVERAGE_BUFFERS:
                getattr(self, name).zero_()

    def turn_about_object(self, camera: int, rotation: torch.Tensor) -> None:
        """Turn camera `camera` about the object centre by [3] axis-angle `rotation` in its own frame (z: about the
        axis through the object centre parallel to the optical axis, a roll when the object is in the middle of the
        view; x and y: an orbit), whatever the parameterization: the current corrections are folded into the base
        poses first (`rebase`)."""
        self.rebase()
        with torch.no_grad():
            turn = torch.zeros(1, 6, dtype=self.base_viewmats.dtype, device=self.base_viewmats.device)
            turn[0, :3] = rotation
            self.base_viewmats[camera] = corrected_viewmats("object", self.base_viewmats[camera:camera + 1], turn,
                                                            self.object_centers[camera:camera + 1])[0]

    def anchor_loss(self, views: torch.Tensor) -> torch.Tensor:
        """Mean over cameras `views` ([B] long) of 1/2 |corrections|^2: after a `rebase`, a differentiable pull of
        those cameras towards where they were then (`camera.round_anchor`). A mean, not a sum: with B views per step
        each camera pays 1/B, the scale at which the anchor's weight was measured."""
        return 0.5 * (self.params()[views] ** 2).sum(-1).mean()

    def set_learning_rate(self, lr: float) -> None:
        for group in self.optimizer.param_groups:
            group["lr"] = lr * (self.settings.translation_scale if group["name"] == "translation" else 1.0)

    def step(self, views: torch.Tensor | None = None) -> None:
        """One Adam step of the cameras in `views` (default all); the others keep their values and Adam moments.

        Adam would move a camera that was not rendered this step through its momentum (its gradient row is zero,
        not absent, or a term such as the epipolar one gives it a gradient): those rows are put back after the
        step, and on a first step (after a reset) their moments stay zero. Adam's step count is the optimizer's,
        not each camera's (as with gsplat's SelectiveAdam): with one view per step, a camera's bias corrections
        are those of more steps than it took.
        """
        if views is None or len(views) == self.num_cameras:
            self.optimizer.step()
            return
        resting = torch.ones(self.num_cameras, dtype=torch.bool, device=self.base_viewmats.device)
        resting[views] = False
        kept = []
        for param in (self.rotations, self.translations):
            state = self.optimizer.state.get(param, {})
            rows = ({key: value[resting].clone() for key, value in state.items()
                     if torch.is_tensor(value) and value.dim() == 2} if state else
                    {key: torch.zeros_like(param.detach()[resting]) for key in ("exp_avg", "exp_avg_sq")})
            kept.append((param, param.detach()[resting].clone(), rows))
        self.optimizer.step()
        with torch.no_grad():
            for param, values, rows in kept:
                param[resting] = values
                state = self.optimizer.state[param]
                for key, value in rows.items():
                    if key in state:  # a parameter without a gradient has no Adam state yet
                        state[key][resting] = value

    def refine(self, loss_of: Callable[[torch.Tensor], torch.Tensor], iterations: int) -> None:
        """Minimize `loss_of(viewmats)` over the corrections by L-BFGS with a strong-Wolfe line search, for poses
        against a model that holds still (test-pose refinement: the Gaussians frozen).

        Adam suits training, where the Gaussians move with the poses, but it steps about its learning rate whatever
        the gradient's size, so against a fixed model it wanders along the directions the images barely constrain
        (a turn about a distant object and the matching image shift). On the telephoto synthetic scene, against
        Gaussians fitted for 200 iterations at the true poses, poses started 1 / 2 / 5 deg off end 1.63 / 6.17 /
        23 deg off after 100 Adam steps and at 0.13 / 0.13 / 0.14 deg after L-BFGS (`bench/pose_optimum.py
        --optimizer`).

        Args:
            loss_of: [C, 4, 4] corrected world-to-camera matrices of every camera -> scalar loss. A camera it does
                not use gets no gradient and stays where it is.
            iterations: L-BFGS iterations (each one or more evaluations of `loss_of`; fewer when it converges).
        """
        # torch's default evaluation budget, 5/4 of the iterations, left one or two iterations a single line-search
        # step (2 iterations did what 1 did); from 12 iterations on it is the default
        optimizer = torch.optim.LBFGS([self.rotations, self.translations], lr=1.0, max_iter=iterations,
                                      max_eval=max(iterations * 5 // 4, iterations + 3), history_size=20,
                                      line_search_fn="strong_wolfe")

        def closure() -> torch.Tensor:
            optimizer.zero_grad()
            loss = loss_of(self())
            loss.backward()
            return loss

        optimizer.step(closure)
        self.zero_grad()

    def zero_grad(self, set_to_none: bool = True) -> None:
        self.optimizer.zero_grad(set_to_none=set_to_none)

    def reset_moments(self) -> None:
        """Clear Adam's moments (a warm restart of the schedule)."""
        self.optimizer.state.clear()

    def state(self) -> dict:
        """Checkpoint content: parameters, buffers and optimizer state, as live tensors (the optimizer's moments
        go on changing with each step: `copy.deepcopy` it to keep a snapshot in memory)."""
        return {"module": self.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state(self, state: dict) -> None:
        module = dict(state["module"])
        if "viewmats_init" in module:  # a checkpoint of a warpbags before the buffer was named for what it holds
            module["base_viewmats"] = module.pop("viewmats_init")
        for name in AVERAGE_BUFFERS:  # a checkpoint of a warpbags before the average has none
            module.setdefault(name, torch.zeros_like(getattr(self, name)))
        self.load_state_dict(module)
        self.optimizer.load_state_dict(state["optimizer"])


def hypothesis_turns(axes: str, angles_deg: tuple[float, ...]) -> list[tuple[str, torch.Tensor]]:
    """(label, [3] float64 axis-angle) of every turn by +-each of `angles_deg` about each of `axes` ("x", "y", "z" of
    a camera's frame), for `CameraOptimizer.turn_about_object`; smaller angles first. A half turn is listed once: both
    ways it is the same rotation, and each turn trains a whole round."""
    turns = []
    for angle in sorted(angles_deg):
        for axis in axes:
            for sign in (1,) if angle == 180 else (1, -1):
                rotation = torch.zeros(3, dtype=torch.float64)
                rotation["xyz".index(axis)] = sign * math.radians(angle)
                turns.append((f"{sign * angle:+g} deg about {axis}", rotation))
    return turns
