"""The trained model: a dict of raw 3DGS parameters, how it renders, and its standard PLY file.

Raw parameters (what the optimizer sees), N Gaussians:
    means [N,3], scales [N,3] (log), quats [N,4] (w, x, y, z, unnormalized), opacities [N] (logit),
    sh0 [N,1,3] (degree-0 SH), shN [N,K-1,3] (higher degrees; absent for degree 0).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from warpbags.errors import WarpbagsError
from warpbags.files import atomic_output
from warpbags.rendering import rasterization

PARAMETER_NAMES = ("means", "scales", "quats", "opacities", "sh0", "shN")


def sh_coefficients(params: dict[str, torch.Tensor]) -> torch.Tensor:
    """[N,K,3] all SH coefficients."""
    return params["sh0"] if "shN" not in params else torch.cat([params["sh0"], params["shN"]], dim=1)


def render_gaussians(
    params: dict[str, torch.Tensor],
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    *,
    sh_degree: int,
    backgrounds: torch.Tensor | None = None,
    pose_deltas: torch.Tensor | None = None,
    render_mode: str = "RGB",
    cpu_threads: int | None = None,
):
    """`warpbags.rasterization` of raw parameters (activations applied here); returns its (colors, alphas, meta)."""
    return rasterization(
        params["means"], params["quats"], params["scales"].exp(), torch.sigmoid(params["opacities"]),
        sh_coefficients(params), viewmats, Ks, width, height, sh_degree=sh_degree, backgrounds=backgrounds,
        pose_deltas=pose_deltas, render_mode=render_mode, cpu_threads=cpu_threads,
    )


def _ply_names(rest_count: int) -> list[str]:
    return (["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)]
            + [f"f_rest_{i}" for i in range(rest_count)] + ["opacity"] + [f"scale_{i}" for i in range(3)]
            + [f"rot_{i}" for i in range(4)])


def write_ply(path: str | Path, params: dict[str, torch.Tensor]) -> None:
    """Write Gaussians as a binary little-endian PLY in the standard 3DGS layout (atomically: temp + rename).

    Properties: x y z nx ny nz f_dc_0..2 f_rest_0..(3(K-1)-1) opacity scale_0..2 rot_0..3, with f_rest in 3DGS's
    channel-major order, opacity as a logit and scales as logs (the raw parameters), as splat viewers expect.
    """
    path = Path(path)
    means = params["means"].detach().cpu().float()
    count = len(means)
    sh0 = params["sh0"].detach().cpu().float().transpose(1, 2).reshape(count, -1)
    shN = params.get("shN")
    rest = torch.zeros(count, 0) if shN is None else shN.detach().cpu().float().transpose(1, 2).reshape(count, -1)
    columns = [means, torch.zeros(count, 3), sh0, rest, params["opacities"].detach().cpu().float()[:, None],
               params["scales"].detach().cpu().float(), params["quats"].detach().cpu().float()]
    data = torch.cat(columns, dim=1).numpy().astype("<f4")
    header = "ply\nformat binary_little_endian 1.0\nelement vertex {}\n{}end_header\n".format(
        count, "".join(f"property float {name}\n" for name in _ply_names(rest.shape[1]))
    )
    with atomic_output(path) as temporary, open(temporary, "wb") as handle:
        handle.write(header.encode("ascii"))
        handle.write(data.tobytes())


def read_ply(path: str | Path) -> dict[str, torch.Tensor]:
    """Read a 3DGS PLY (as written by `write_ply` or 3DGS itself) back into raw parameters.

    Raises:
        WarpbagsError: not a binary little-endian PLY with the 3DGS float properties.
    """
    path = Path(path)
    try:
        with open(path, "rb") as handle:
            header = b""
            while not header.endswith(b"end_header\n"):
                line = handle.readline()
                if not line:
                    raise WarpbagsError(f"{path}: no PLY end_header")
                header += line
            lines = header.decode("ascii").splitlines()
            if lines[0] != "ply" or "format binary_little_endian 1.0" not in lines:
                raise WarpbagsError(f"{path}: not a binary little-endian PLY")
            count = int(next(line.split()[2] for line in lines if line.startswith("element vertex")))
            names = [line.split()[2] for line in lines if line.startswith("property float")]
            data = np.frombuffer(handle.read(), dtype="<f4")
    except (OSError, UnicodeDecodeError, StopIteration, ValueError, IndexError) as error:
        raise WarpbagsError(f"{path}: unreadable PLY ({error})") from None
    rest_count = sum(name.startswith("f_rest_") for name in names)
    if names != _ply_names(rest_count) or data.size != count * len(names) or rest_count % 3:
        raise WarpbagsError(f"{path}: not a 3DGS Gaussian PLY ({len(names)} float properties, {data.size} values)")
    table = torch.from_numpy(data.reshape(count, len(names)).copy())
    column = {name: index for index, name in enumerate(names)}

    def take(prefix: str, n: int) -> torch.Tensor:
        return table[:, column[f"{prefix}0"]: column[f"{prefix}0"] + n]

    params = {
        "means": table[:, 0:3].contiguous(),
        "scales": take("scale_", 3).contiguous(),
        "quats": take("rot_", 4).contiguous(),
        "opacities": table[:, column["opacity"]].contiguous(),
        "sh0": take("f_dc_", 3)[:, None, :].contiguous(),
    }
    if rest_count:
        params["shN"] = take("f_rest_", rest_count).reshape(count, 3, rest_count // 3).transpose(1, 2).contiguous()
    return params


def sh_degree_of(params: dict[str, torch.Tensor]) -> int:
    """The highest SH degree the parameters hold."""
    count = 1 + (params["shN"].shape[1] if "shN" in params else 0)
    return int(round(count**0.5)) - 1


def to_source_frame(params: dict[str, torch.Tensor], center, scale: float) -> dict[str, torch.Tensor]:
    """Parameters moved from the normalized world (x' = scale (x - center)) back to the scene's source frame.

    Means are un-normalized and log-scales shifted by -log(scale); rotations, opacities and SH are unchanged (a
    uniform scale and a translation keep view directions).
    """
    out = dict(params)
    out["means"] = params["means"] / scale + torch.as_tensor(center, dtype=params["means"].dtype)
    out["scales"] = params["scales"] - math.log(scale)
    return out
