"""The trained model: a dict of raw 3DGS parameters, how it renders, and its standard PLY file.

Raw parameters (what the optimizer sees), N Gaussians:
    means [N,3], scales [N,3] (log), quats [N,4] (w, x, y, z, unnormalized), opacities [N] (logit),
    sh0 [N,1,3] (degree-0 SH), shN [N,K-1,3] (higher degrees; absent for degree 0).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch

from warpbags.data.scene import SceneNormalization
from warpbags.errors import WarpbagsError
from warpbags.files import atomic_output
from warpbags.rendering import rasterization


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


# PLY property types as numpy little-endian dtypes (both the spec's names and the sized aliases tools write).
_PLY_TYPES = {"char": "i1", "uchar": "u1", "short": "<i2", "ushort": "<u2", "int": "<i4", "uint": "<u4",
              "float": "<f4", "double": "<f8", "int8": "i1", "uint8": "u1", "int16": "<i2", "uint16": "<u2",
              "int32": "<i4", "uint32": "<u4", "float32": "<f4", "float64": "<f8"}
_REQUIRED_PROPERTIES = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                        "rot_0", "rot_1", "rot_2", "rot_3")


def _read_vertex_table(path: Path) -> np.ndarray:
    """The vertex element of a binary little-endian PLY as a structured array (one field per property)."""
    with open(path, "rb") as handle:
        header = handle.readline(8)  # bounded: a large binary file of another kind has no early newline
        if header != b"ply\n":
            raise WarpbagsError(f"{path}: not a PLY file")
        while not header.endswith(b"end_header\n"):
            line = handle.readline()
            if not line:
                raise WarpbagsError(f"{path}: no PLY end_header")
            header += line
        lines = header.decode("latin-1").splitlines()  # a comment may hold any bytes; the keywords are ASCII
        if "format binary_little_endian 1.0" not in lines:
            raise WarpbagsError(f"{path}: not a binary little-endian PLY")
        elements = [index for index, line in enumerate(lines) if line.startswith("element ")]
        if not elements or lines[elements[0]].split()[1] != "vertex":
            raise WarpbagsError(f"{path}: the first PLY element is not vertex")
        count = int(lines[elements[0]].split()[2])
        end = elements[1] if len(elements) > 1 else len(lines)
        fields = []
        for line in lines[elements[0] + 1:end]:
            words = line.split()
            if words[0] == "property":
                if words[1] == "list" or words[1] not in _PLY_TYPES:
                    raise WarpbagsError(f"{path}: unsupported vertex property {line!r}")
                fields.append((words[2], _PLY_TYPES[words[1]]))
        dtype = np.dtype(fields)
        # a header claiming more vertices than the file holds is cut short, not a read of that many bytes
        available = os.fstat(handle.fileno()).st_size - handle.tell()
        data = handle.read(min(count * dtype.itemsize, max(available, 0)))  # later elements (faces) are not needed
    if len(data) != count * dtype.itemsize:
        raise WarpbagsError(f"{path}: truncated PLY ({len(data)} of {count * dtype.itemsize} vertex bytes)")
    return np.frombuffer(data, dtype=dtype, count=count)


def read_ply(path: str | Path) -> dict[str, torch.Tensor]:
    """Read a 3DGS PLY back into raw parameters: as written by `write_ply`, 3DGS, gsplat, nerfstudio and others.

    Properties are read by name, in any order and of any numeric type; others (normals, colours) are ignored.
    Needed: x y z, f_dc_0..2, opacity (logit), scale_0..2 (log), rot_0..3 (w, x, y, z); f_rest_* are optional
    (3DGS's channel-major order).

    Raises:
        WarpbagsError: not a binary little-endian PLY with the 3DGS properties, one of no Gaussians, or one with a
            value that is not finite (named with its property and Gaussian).
    """
    path = Path(path)
    try:
        table = _read_vertex_table(path)
    except (OSError, UnicodeDecodeError, ValueError, IndexError, TypeError) as error:
        raise WarpbagsError(f"{path}: unreadable PLY ({error})") from None
    if len(table) == 0:  # a valid header of no vertices: nothing to render, export or align
        raise WarpbagsError(f"{path}: the PLY holds no Gaussians (element vertex 0)")
    names = table.dtype.names
    rest_count = sum(name.startswith("f_rest_") for name in names)
    # f_rest_0 .. f_rest_{n-1}, whatever their order in the header
    missing = [name for name in (*_REQUIRED_PROPERTIES, *(f"f_rest_{i}" for i in range(rest_count)))
               if name not in names]
    coefficients = 1 + rest_count // 3  # per colour channel: (degree + 1)^2 for degree 0-3
    if missing or rest_count % 3 or coefficients not in (1, 4, 9, 16):
        raise WarpbagsError(f"{path}: not a 3DGS Gaussian PLY (missing {', '.join(missing) or 'none'}; "
                            f"{rest_count} f_rest properties, where SH degrees 0-3 have 0, 9, 24 or 45)")

    def columns(*column_names: str) -> torch.Tensor:
        arrays = [table[name].astype(np.float32) for name in column_names]
        for name, values in zip(column_names, arrays):
            bad = np.flatnonzero(~np.isfinite(values))
            if len(bad):  # a NaN centre renders nothing: a picture of the background, not an error
                raise WarpbagsError(f"{path}: {name} of Gaussian {bad[0]} is {values[bad[0]]} ({len(bad)} of "
                                    f"{len(values)} not finite)")
        return torch.from_numpy(np.stack(arrays, axis=1))

    count = len(table)
    params = {
        "means": columns("x", "y", "z"),
        "scales": columns("scale_0", "scale_1", "scale_2"),
        "quats": columns("rot_0", "rot_1", "rot_2", "rot_3"),
        "opacities": columns("opacity")[:, 0].contiguous(),
        "sh0": columns("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :],
    }
    if rest_count:
        rest = columns(*(f"f_rest_{i}" for i in range(rest_count)))
        params["shN"] = rest.reshape(count, 3, rest_count // 3).transpose(1, 2).contiguous()
    return params


def opacity_weighted_center(params: dict[str, torch.Tensor]) -> torch.Tensor:
    """[3] the Gaussians' centres averaged with their opacities as weights: where the object is."""
    weights = torch.sigmoid(params["opacities"])[:, None]
    return (params["means"] * weights).sum(0) / weights.sum().clamp_min(1e-12)


def object_points(params: dict[str, torch.Tensor], count: int = 20_000) -> torch.Tensor:
    """[N, 3] centres of the Gaussians at least half opaque (all of them where none is), every k-th of them so that
    at most `count` remain: points on the object, for measures that project it."""
    means = params["means"]
    opaque = means[torch.sigmoid(params["opacities"]) > 0.5]
    points = opaque if len(opaque) else means
    return points[::max(1, -(-len(points) // count))]


def sh_degree_of(params: dict[str, torch.Tensor]) -> int:
    """The highest SH degree the parameters hold."""
    count = 1 + (params["shN"].shape[1] if "shN" in params else 0)
    return int(round(count**0.5)) - 1


def to_source_frame(params: dict[str, torch.Tensor], normalization: SceneNormalization) -> dict[str, torch.Tensor]:
    """Parameters moved from the normalized world (x' = scale (x - center)) back to the scene's source frame.

    Means are un-normalized and log-scales shifted by -log(scale); rotations, opacities and SH are unchanged (a
    uniform scale and a translation keep view directions).
    """
    out = dict(params)
    out["means"] = normalization.invert_points(params["means"])
    out["scales"] = params["scales"] - math.log(normalization.scale)
    return out
