"""Random rotations, poses and similarities for the pose-maths tests, built without the code under test.

Rotations come from torch's matrix exponential of cross-product matrices written out entry by entry, so tests of
`warpbags.lie` stay independent of it.
"""

from __future__ import annotations

import torch

from warpbags.alignment import Sim3

F64 = torch.float64


def generator(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def unit_vectors(n: int, gen: torch.Generator) -> torch.Tensor:
    vectors = torch.randn(n, 3, generator=gen, dtype=F64)
    return vectors / vectors.norm(dim=-1, keepdim=True)


def skew_reference(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrix written out entry by entry (independent of the module's helper)."""
    k = torch.zeros(*v.shape[:-1], 3, 3, dtype=v.dtype)
    k[..., 0, 1], k[..., 0, 2] = -v[..., 2], v[..., 1]
    k[..., 1, 0], k[..., 1, 2] = v[..., 2], -v[..., 0]
    k[..., 2, 0], k[..., 2, 1] = -v[..., 1], v[..., 0]
    return k


def twist_matrix(xi: torch.Tensor) -> torch.Tensor:
    """4x4 matrix [[skew(w), v], [0, 0]] of a twist [w, v]."""
    t = torch.zeros(*xi.shape[:-1], 4, 4, dtype=xi.dtype)
    t[..., :3, :3] = skew_reference(xi[..., :3])
    t[..., :3, 3] = xi[..., 3:]
    return t


def random_rotations(n: int, gen: torch.Generator) -> torch.Tensor:
    """Rotations from the matrix exponential (not from so3_exp, so tests of so3_exp stay independent)."""
    omega = torch.randn(n, 3, generator=gen, dtype=F64) * 1.5
    return torch.linalg.matrix_exp(skew_reference(omega))


def random_viewmats(n: int, gen: torch.Generator) -> torch.Tensor:
    rotations = random_rotations(n, gen)
    centers = torch.randn(n, 3, generator=gen, dtype=F64) * 3.0
    viewmats = torch.eye(4, dtype=F64).repeat(n, 1, 1)
    viewmats[:, :3, :3] = rotations
    viewmats[:, :3, 3] = -(rotations @ centers[..., None])[..., 0]
    return viewmats


def random_sim3(gen: torch.Generator, scale: float = 2.7) -> Sim3:
    rotation = random_rotations(1, gen)[0]
    translation = torch.randn(3, generator=gen, dtype=F64) * 5.0
    return Sim3(torch.tensor(scale, dtype=F64), rotation, translation)
