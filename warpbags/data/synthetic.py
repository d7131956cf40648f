"""A synthetic object-centric 360-degree scene with exact poses, masks and depth maps.

One of two objects built from textured boxes, spheres and cylinders, rendered by an analytic ray caster in numpy
(independent of the splatting kernels), Lambertian shading, white background: a toy excavator (tracks, body, cab,
boom, stick, bucket, counterweight) on a base slab, textured with scikit-image's bundled photographs, whose
silhouette differs from every side; or a wooden tankard lying on its side (a staved cylinder, three hoops, a lid,
a flat handle) in procedural wood, shaped and textured like the maryrose capture: a nearly symmetric silhouette and
a low-contrast, repetitive grain. Cameras sit on a dome around the object. The scene is written in the MipNeRF360 /
GaussianObject layout, so `load_scene` reads it like a capture:

    images/view_XXX.png   masks/view_XXX.png   depths/view_XXX.npy (z-depth, world units, 0 = background)
    sparse/0/{cameras,images,points3D}.bin     sparse_{4,6,9,test}.txt     synthetic.json

Texture sources of the excavator (all bundled with scikit-image): brick, grass, gravel (CC0), coffee, chelsea (CC0),
astronaut (public domain, NASA). The tankard's wood is generated (`_wood_texture`).

It stays one module because it is one generator: the objects, the ray caster that renders only their
primitives, the dome of cameras and the writer of the folder, used nowhere else.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import cv2
import numpy as np
import torch

from warpbags.cameras import camera_centers
from warpbags.data.colmap import write_model
from warpbags.data.scene import DEFAULT_SPLIT_SIZES, farthest_views
from warpbags.errors import WarpbagsError, one_line, sigterm_stops
from warpbags.files import writable_folder, write_image
from warpbags.lie import so3_exp

GENERATOR_VERSION = 3  # bump whenever the geometry or rendering changes: cache folders are keyed on it
MAX_SIZE = 2048  # pixels a side: a view is rendered at once, about 1 GB of memory per million pixels (supersample 2)
MAX_VIEWS = 1000
MAX_GAIN_JITTER = 1.0  # exp(N(0, 1)) scales a channel by 0.37-2.7 at one sigma: darker or brighter than any camera
BACKGROUND = 1.0  # white
LIGHT_DIRECTION = np.array([0.4, -0.3, 0.87]) / np.linalg.norm([0.4, -0.3, 0.87])
LIGHT_IN_CAMERA = np.array([-0.7, -0.4, -0.6]) / np.linalg.norm([-0.7, -0.4, -0.6])
"""The light of `SyntheticOptions.turntable_light`, in camera axes (OpenCV: x right, y down, z forward): to the
camera's left, above it and on its side of the object, as a studio key light beside a turntable."""


@dataclass(frozen=True)
class SyntheticOptions:
    """Generator settings.

    Attributes:
        views: number of cameras on the dome (32-100 for real use; fewer is allowed for tests).
        width, height: image size in pixels.
        seed: seeds the sampled SfM points, each view's light and colour gains where they are jittered, and the
            textures: the tankard's wood grain, and the excavator's crops of its non-square photographs (coffee,
            chelsea; its square ones are used whole, whatever the seed).
        radius: camera distance from the object centre (world units; the loader normalizes it away).
        fov_deg: horizontal field of view.
        min_elevation_deg, max_elevation_deg: camera elevation range above the base plane.
        supersample: colour is averaged over supersample^2 rays per pixel (masks and depth use the pixel centre).
        num_points: SfM-like points written to points3D.bin (unprojected from the depth maps).
        light_jitter_deg: each view's light direction is turned from `LIGHT_DIRECTION` by up to this angle (uniform,
            about a random axis): the shading changes from view to view, as on a capture whose object was moved
            between sequences under fixed lights.
        gain_jitter: each view's colour channels are scaled by exp(N(0, gain_jitter^2)) (exposure and white
            balance changing between shots). The background stays white; masks and depth maps do not change.
        turntable_light: the light turns with the camera (`LIGHT_IN_CAMERA` in each view's camera axes), as on a
            turntable capture, where the object turns under lights that stand still with the camera (maryrose): the
            shading of each part of the object changes with the side it is seen from. Jitter turns it further.
        object: which object the scene shows, a key of `OBJECTS` ("excavator" or "tankard").
    """

    views: int = 48
    width: int = 256
    height: int = 256
    seed: int = 0
    radius: float = 3.6
    fov_deg: float = 45.0
    min_elevation_deg: float = 10.0
    max_elevation_deg: float = 60.0
    supersample: int = 2
    num_points: int = 4000
    light_jitter_deg: float = 0.0
    gain_jitter: float = 0.0
    turntable_light: bool = False
    object: str = "excavator"

    def folder_name(self) -> str:
        """The cache folder's name: every setting that changes the scene (defaults of optics and orbit left out, so
        the folders of older versions keep their names)."""
        name = f"synthetic-v{GENERATOR_VERSION}-{self.views}views-{self.width}x{self.height}-seed{self.seed}"
        defaults = SyntheticOptions()
        for field in ("fov_deg", "radius", "min_elevation_deg", "max_elevation_deg", "supersample", "num_points",
                      "light_jitter_deg", "gain_jitter", "turntable_light", "object"):
            if getattr(self, field) != getattr(defaults, field):
                value = getattr(self, field)
                name += f"-{field.replace('_deg', '')}{value if isinstance(value, str) else format(value, 'g')}"
        return name


OBJECT_CENTER = np.array([0.3, -0.2, 0.45])
"""World position the cameras look at (deliberately off the origin so normalization has work to do)."""


@dataclass
class Primitive:
    """A textured solid: kind "box" (size = half extents), "sphere" (size[0] = radius) or "cylinder" along local z
    (size = radius, radius, half height). `rotation` maps local to world axes, `center` is in world."""

    kind: str
    center: np.ndarray
    rotation: np.ndarray
    size: np.ndarray
    texture: np.ndarray  # [h,w,3] float32 RGB
    tiles: float = 1.0


def _rotation(axis: str, degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def _textures(seed: int) -> dict[str, np.ndarray]:
    from skimage import data

    rng = np.random.default_rng(seed)

    def prepare(image: np.ndarray, tint=(1.0, 1.0, 1.0), size: int = 128) -> np.ndarray:
        image = image.astype(np.float32) / (255.0 if image.dtype == np.uint8 else 1.0)
        if image.ndim == 2:
            image = np.repeat(image[:, :, None], 3, axis=2)
        image = image[:, :, :3]
        side = min(image.shape[:2])
        top = rng.integers(0, image.shape[0] - side + 1)
        left = rng.integers(0, image.shape[1] - side + 1)
        image = cv2.resize(image[top : top + side, left : left + side], (size, size), interpolation=cv2.INTER_AREA)
        return np.clip(image * np.asarray(tint, np.float32), 0, 1)

    return {
        "yellow": prepare(data.brick(), (1.25, 1.0, 0.25)),
        "tracks": prepare(data.gravel(), (0.5, 0.5, 0.55)),
        "base": prepare(data.grass(), (0.7, 0.9, 0.6)),
        "coffee": prepare(data.coffee()),
        "cat": prepare(data.chelsea()),
        "astronaut": prepare(data.astronaut()),
    }


def build_excavator(seed: int = 0) -> list[Primitive]:
    """The primitives of the toy excavator, in world coordinates (base top at z = 0.1, about 1.4 units long)."""
    textures = _textures(seed)
    identity = np.eye(3)
    offset = OBJECT_CENTER - np.array([0.0, 0.0, 0.45])

    def make(kind, center, rotation, size, texture, tiles=1.0):
        center = np.asarray(center, float) + offset
        return Primitive(kind, center, rotation, np.asarray(size, float), textures[texture], tiles)

    boom_rotation = _rotation("y", -35.0)  # up and forward from the body
    stick_rotation = _rotation("y", -21.0)  # from the boom tip down to the bucket
    return [
        make("box", (0.0, 0.0, 0.05), identity, (0.9, 0.7, 0.05), "base", 2.0),
        make("box", (0.0, 0.3, 0.2), identity, (0.5, 0.1, 0.1), "tracks", 2.0),
        make("box", (0.0, -0.3, 0.2), identity, (0.5, 0.1, 0.1), "tracks", 2.0),
        make("cylinder", (0.0, 0.0, 0.33), identity, (0.18, 0.18, 0.03), "tracks"),
        make("box", (-0.05, 0.0, 0.48), _rotation("z", 10.0), (0.35, 0.25, 0.12), "yellow"),
        make("box", (0.12, 0.12, 0.72), identity, (0.12, 0.11, 0.12), "astronaut"),
        make("cylinder", (-0.38, 0.0, 0.5), _rotation("x", 90.0), (0.12, 0.12, 0.22), "coffee"),
        make("box", (0.42, -0.08, 0.75), boom_rotation, (0.3, 0.05, 0.05), "yellow"),
        make("box", (0.76, -0.08, 0.685), stick_rotation, (0.05, 0.05, 0.26), "yellow"),
        make("sphere", (0.85, -0.08, 0.42), identity, (0.12, 0.12, 0.12), "cat"),
    ]


def _wood_texture(rng: np.random.Generator, tint, staves: int = 0, size: int = 128) -> np.ndarray:
    """[size,size,3] wood: a grain of fine streaks along the rows' direction (texture v, a cylinder's axis), split
    into `staves` bands across u of slightly different tones with dark seams between them (0: one board)."""
    grain = cv2.GaussianBlur(rng.normal(size=(size, size)).astype(np.float32), (0, 0), sigmaX=0.7, sigmaY=6.0)
    shade = 1.0 + 0.12 * grain / grain.std()
    if staves:
        band = (np.arange(size) * staves) // size
        shade = shade * rng.uniform(0.85, 1.1, size=staves)[band][None, :]
        seams = np.nonzero(np.diff(band))[0] + 1
        shade[:, seams] *= 0.55
    return np.clip(shade[:, :, None] * np.asarray(tint, np.float32), 0, 1)


def build_tankard(seed: int = 0) -> list[Primitive]:
    """The primitives of the wooden tankard lying on its side, in world coordinates (about 1.5 units long, its axis
    along world x, filling the telephoto views as maryrose's fills hers): a staved body, three hoops, a lid on one
    end and a flat handle along one side, past that end."""
    rng = np.random.default_rng([seed, 2])
    staves = _wood_texture(rng, (0.72, 0.52, 0.25), staves=14)
    hoop = _wood_texture(rng, (0.60, 0.42, 0.20))
    dark = _wood_texture(rng, (0.42, 0.30, 0.17))
    along_x = _rotation("y", 90.0)  # a cylinder's local z axis onto world x
    scale = 1.3

    def make(kind, axial, size, texture, side=0.0, rotation=along_x):
        center = OBJECT_CENTER + scale * np.array([axial, side, 0.0])
        return Primitive(kind, center, rotation, scale * np.asarray(size, float), texture)

    return [
        make("cylinder", 0.0, (0.36, 0.36, 0.48), staves),
        make("cylinder", -0.38, (0.385, 0.385, 0.035), hoop),
        make("cylinder", 0.30, (0.385, 0.385, 0.035), hoop),
        make("cylinder", 0.40, (0.385, 0.385, 0.035), hoop),
        make("cylinder", -0.50, (0.30, 0.30, 0.02), dark),
        make("box", -0.45, (0.30, 0.03, 0.12), dark, side=-0.39, rotation=np.eye(3)),
    ]


OBJECTS = {"excavator": build_excavator, "tankard": build_tankard}
"""The objects a synthetic scene can show, by `SyntheticOptions.object`: each builds its primitives from a seed."""


def _intersect(primitive: Primitive, origins: np.ndarray, directions: np.ndarray):
    """Ray-solid intersection. Returns t [N] (inf where missed), local hit points [N,3], local normals [N,3]."""
    local_origins = (origins - primitive.center) @ primitive.rotation
    local_directions = directions @ primitive.rotation
    count = len(origins)
    t = np.full(count, np.inf)
    normals = np.zeros((count, 3))
    eps = 1e-9
    if primitive.kind == "box":
        half = primitive.size
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-half - local_origins) / local_directions
            t2 = (half - local_origins) / local_directions
        t_near_axes = np.nan_to_num(np.minimum(t1, t2), nan=-np.inf)
        t_far_axes = np.nan_to_num(np.maximum(t1, t2), nan=np.inf)
        t_near, t_far = t_near_axes.max(1), t_far_axes.min(1)
        hit = (t_near <= t_far) & (t_near > eps)
        axis = t_near_axes.argmax(1)
        t[hit] = t_near[hit]
        rows = np.nonzero(hit)[0]
        normals[rows, axis[rows]] = -np.sign(local_directions[rows, axis[rows]])
    elif primitive.kind == "sphere":
        radius = primitive.size[0]
        b = np.einsum("ij,ij->i", local_origins, local_directions)
        c = np.einsum("ij,ij->i", local_origins, local_origins) - radius**2
        disc = b * b - c
        root = -b - np.sqrt(np.maximum(disc, 0))
        hit = (disc >= 0) & (root > eps)
        t[hit] = root[hit]
        with np.errstate(invalid="ignore"):  # a missing ray's t is inf: inf * 0 where its direction has a zero
            normals = (local_origins + t[:, None] * local_directions) / radius
    else:  # cylinder along local z
        radius, half_height = primitive.size[0], primitive.size[2]
        ox, oy, oz = local_origins.T
        dx, dy, dz = local_directions.T
        a = dx * dx + dy * dy
        b = ox * dx + oy * dy
        c = ox * ox + oy * oy - radius**2
        disc = b * b - a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            side = (-b - np.sqrt(np.maximum(disc, 0))) / a
        side_ok = (disc >= 0) & (a > 1e-12) & (side > eps) & (np.abs(oz + side * dz) <= half_height)
        t = np.where(side_ok, side, np.inf)
        for cap in (-half_height, half_height):
            with np.errstate(divide="ignore", invalid="ignore"):
                t_cap = (cap - oz) / dz
            x, y = ox + t_cap * dx, oy + t_cap * dy
            cap_ok = (np.abs(dz) > 1e-12) & (t_cap > eps) & (x * x + y * y <= radius**2) & (t_cap < t)
            t = np.where(cap_ok, t_cap, t)
            normals[cap_ok] = (0.0, 0.0, np.sign(cap))
        on_side = side_ok & (t == side)
        points = local_origins + np.where(np.isfinite(t), t, 0)[:, None] * local_directions
        normals[on_side] = np.stack([points[on_side, 0], points[on_side, 1], np.zeros(on_side.sum())], 1) / radius
    points = local_origins + np.where(np.isfinite(t), t, 0)[:, None] * local_directions
    return t, points, normals


def _texture_coordinates(primitive: Primitive, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    size = primitive.size
    if primitive.kind == "box":
        axis = np.abs(normals).argmax(1)
        other = np.array([[1, 2], [0, 2], [0, 1]])[axis]
        rows = np.arange(len(points))
        u = points[rows, other[:, 0]] / size[other[:, 0]]
        v = points[rows, other[:, 1]] / size[other[:, 1]]
        uv = np.stack([u, v], 1) * 0.5 + 0.5
    elif primitive.kind == "sphere":
        unit = points / size[0]
        longitude = np.arctan2(unit[:, 1], unit[:, 0]) / (2 * np.pi) + 0.5
        uv = np.stack([longitude, np.arccos(np.clip(unit[:, 2], -1, 1)) / np.pi], 1)
    else:
        on_cap = np.abs(normals[:, 2]) > 0.5
        angle = np.arctan2(points[:, 1], points[:, 0]) / (2 * np.pi) + 0.5
        side_uv = np.stack([angle, points[:, 2] / (2 * size[2]) + 0.5], 1)
        cap_uv = points[:, :2] / (2 * size[0]) + 0.5
        uv = np.where(on_cap[:, None], cap_uv, side_uv)
    return uv * primitive.tiles


def _hits_bounding_sphere(primitive: Primitive, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """[N] bool: the ray passes within the primitive's bounding sphere (a cheap pre-test)."""
    size = primitive.size
    bound = np.hypot(size[0], size[2]) if primitive.kind == "cylinder" else np.linalg.norm(size)
    to_center = primitive.center - origins
    along = to_center @ directions if to_center.ndim == 1 else np.einsum("ij,ij->i", to_center, directions)
    squared_distance = np.einsum("ij,ij->i", to_center, to_center) - along**2
    return (squared_distance <= bound**2 * 1.0001) & (along > -bound)


def cast_rays(primitives: list[Primitive], origins: np.ndarray, directions: np.ndarray,
              light: np.ndarray = LIGHT_DIRECTION):
    """First hit of each ray against the scene.

    Args:
        origins, directions: [N,3] world rays (directions unit length).
        light: [3] unit direction of the light (Lambertian shading, two-sided).

    Returns:
        t [N] (inf on a miss), colors [N,3] float shaded RGB (background where missed).
    """
    best_t = np.full(len(origins), np.inf)
    colors = np.full((len(origins), 3), BACKGROUND)
    for primitive in primitives:
        candidates = np.nonzero(_hits_bounding_sphere(primitive, origins, directions))[0]
        if not len(candidates):
            continue
        t, points, normals = _intersect(primitive, origins[candidates], directions[candidates])
        closer = t < best_t[candidates]
        if not closer.any():
            continue
        rays = candidates[closer]
        best_t[rays] = t[closer]
        uv = _texture_coordinates(primitive, points[closer], normals[closer]) % 1.0
        texture = primitive.texture
        rows = np.minimum((uv[:, 1] * texture.shape[0]).astype(int), texture.shape[0] - 1)
        cols = np.minimum((uv[:, 0] * texture.shape[1]).astype(int), texture.shape[1] - 1)
        world_normals = normals[closer] @ primitive.rotation.T
        lambert = np.abs(world_normals @ light)
        colors[rays] = texture[rows, cols] * (0.35 + 0.65 * lambert)[:, None]
    return best_t, np.clip(colors, 0, 1)


def dome_viewmats(options: SyntheticOptions) -> np.ndarray:
    """[C,4,4] world-to-camera poses (OpenCV axes) on a dome around `OBJECT_CENTER`, z up, looking at it."""
    golden = (np.sqrt(5.0) - 1.0) / 2.0
    viewmats = np.tile(np.eye(4), (options.views, 1, 1))
    for index in range(options.views):
        azimuth = 2 * np.pi * index / options.views
        fraction = (index * golden) % 1.0
        elevation_range = options.max_elevation_deg - options.min_elevation_deg
        elevation = np.radians(options.min_elevation_deg + fraction * elevation_range)
        eye = OBJECT_CENTER + options.radius * np.array(
            [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
        )
        forward = (OBJECT_CENTER - eye) / np.linalg.norm(OBJECT_CENTER - eye)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        rotation = np.stack([right, down, forward])  # rows: camera axes in world
        viewmats[index, :3, :3] = rotation
        viewmats[index, :3, 3] = -rotation @ eye
    return viewmats


def intrinsics(options: SyntheticOptions) -> np.ndarray:
    """[3,3] pinhole K, principal point at the image centre (pixel centres at +0.5)."""
    focal = 0.5 * options.width / np.tan(np.radians(options.fov_deg) / 2)
    return np.array([[focal, 0, options.width / 2], [0, focal, options.height / 2], [0, 0, 1.0]])


def render_view(
    primitives: list[Primitive], viewmat: np.ndarray, K: np.ndarray, width: int, height: int, supersample: int,
    light: np.ndarray = LIGHT_DIRECTION, gain: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render one view lit from `light`, the object's colours scaled by [3] `gain` (None: 1). Returns image [H,W,3]
    float32, mask [H,W] float32, z-depth [H,W] float32 (0 = background)."""
    rotation = viewmat[:3, :3]
    eye = camera_centers(torch.from_numpy(viewmat)).numpy()

    def rays(offsets: np.ndarray):
        xs, ys = np.meshgrid(np.arange(width) + 0.0, np.arange(height) + 0.0)
        pixels = np.stack([xs.ravel(), ys.ravel()], 1)[:, None, :] + offsets[None]
        pixels = pixels.reshape(-1, 2)
        camera = np.linalg.solve(K, np.concatenate([pixels, np.ones((len(pixels), 1))], 1).T).T
        camera /= np.linalg.norm(camera, axis=1, keepdims=True)
        return camera, camera @ rotation

    centre_camera, centre_world = rays(np.array([[0.5, 0.5]]))
    t, _ = cast_rays(primitives, np.broadcast_to(eye, centre_world.shape), centre_world)
    hit = np.isfinite(t)
    depth = np.where(hit, t * centre_camera[:, 2], 0.0).reshape(height, width)
    steps = (np.arange(supersample) + 0.5) / supersample
    offsets = np.stack(np.meshgrid(steps, steps), -1).reshape(-1, 2)
    _, sample_world = rays(offsets)
    sample_t, colors = cast_rays(primitives, np.broadcast_to(eye, sample_world.shape), sample_world, light)
    if gain is not None:
        colors = np.where(np.isfinite(sample_t)[:, None], np.clip(colors * gain, 0, 1), colors)
    image = colors.reshape(height, width, len(offsets), 3).mean(2)
    return image.astype(np.float32), hit.reshape(height, width).astype(np.float32), depth.astype(np.float32)


def view_lighting(options: SyntheticOptions, viewmats: np.ndarray) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """Each view's (light direction, colour gain or None) for [C,4,4] world-to-camera `viewmats`: `LIGHT_DIRECTION`,
    or with `options.turntable_light` `LIGHT_IN_CAMERA` in each camera's axes, turned by `light_jitter_deg` and scaled
    by `gain_jitter` from a random stream of its own (the scene's other random draws do not move when they are
    switched on)."""
    lights = ([viewmat[:3, :3].T @ LIGHT_IN_CAMERA for viewmat in viewmats] if options.turntable_light
              else [LIGHT_DIRECTION] * options.views)
    if options.light_jitter_deg == 0 and options.gain_jitter == 0:
        return [(light, None) for light in lights]
    rng = np.random.default_rng([options.seed, 1])
    lighting = []
    for light in lights:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = np.radians(options.light_jitter_deg) * rng.uniform()
        light = so3_exp(torch.from_numpy(axis * angle)).numpy() @ light
        lighting.append((light, np.exp(rng.normal(scale=options.gain_jitter, size=3))))
    return lighting


def generate_synthetic_scene(out_dir: str | Path, options: SyntheticOptions = SyntheticOptions()) -> Path:
    """Render the synthetic scene and write it to `out_dir` (MipNeRF360 layout). Returns `out_dir`.

    Written to a temporary sibling folder first and renamed, so an interrupted run leaves no partial scene.

    Raises:
        WarpbagsError: an option out of range or not finite, or an `out_dir` that cannot take the scene; before
            anything is written.
    """
    out_dir = Path(out_dir).resolve()  # "." has no name to build the staging folder's from
    for field in fields(options):  # first: NaN passes every range check below
        value = getattr(options, field.name)
        if isinstance(value, float) and not math.isfinite(value):
            raise WarpbagsError(f"synthetic scene {field.name} must be a finite number, got {value}")
    if options.views < 4 or options.width < 8 or options.height < 8:
        raise WarpbagsError(
            f"synthetic scene needs at least 4 views and 8x8 pixels, "
            f"got {options.views} views of {options.width}x{options.height}"
        )
    if options.views > MAX_VIEWS or max(options.width, options.height) > MAX_SIZE:
        raise WarpbagsError(
            f"synthetic scene takes at most {MAX_VIEWS} views and {MAX_SIZE} pixels a side (a view is rendered at "
            f"once, about 1 GB of memory per million pixels), got {options.views} views of "
            f"{options.width}x{options.height}"
        )
    if options.seed < 0:
        raise WarpbagsError(f"synthetic scene seed must be >= 0, got {options.seed}")
    if options.object not in OBJECTS:
        raise WarpbagsError(f"unknown synthetic object {options.object!r}: choose one of {', '.join(OBJECTS)}")
    if not (0 <= options.light_jitter_deg <= 180 and 0 <= options.gain_jitter <= MAX_GAIN_JITTER):
        raise WarpbagsError(f"light jitter must be in [0, 180] deg and gain jitter in [0, {MAX_GAIN_JITTER:g}], got "
                            f"{options.light_jitter_deg} and {options.gain_jitter}")
    writable_folder(out_dir, "to write the scene into")
    if out_dir.exists() and any(out_dir.iterdir()):
        raise WarpbagsError(f"{out_dir} exists and is not empty")
    staging = out_dir.with_name(f".{out_dir.name}.partial-{os.getpid()}")
    shutil.rmtree(staging, ignore_errors=True)
    try:
        with sigterm_stops():
            _write_scene(staging, options)
        if out_dir.exists():  # an empty folder, perhaps the caller's own: filled, not replaced
            for entry in staging.iterdir():
                os.replace(entry, out_dir / entry.name)
        else:
            out_dir.parent.mkdir(parents=True, exist_ok=True)
            os.replace(staging, out_dir)
    except OSError as error:  # a full disk, a folder root may not write into after all
        raise WarpbagsError(f"cannot write the scene into {out_dir}: {one_line(error)}") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return out_dir


def _write_scene(staging: Path, options: SyntheticOptions) -> None:
    """Render the scene of `options` and write its files into the new folder `staging`."""
    for folder in ("images", "masks", "depths"):
        (staging / folder).mkdir(parents=True)
    primitives = OBJECTS[options.object](options.seed)
    viewmats = dome_viewmats(options)
    K = intrinsics(options)
    names = [f"view_{index:03d}.png" for index in range(options.views)]
    rng = np.random.default_rng(options.seed)
    points, colors = [], []
    per_view = max(1, options.num_points // options.views)
    for name, viewmat, (light, gain) in zip(names, viewmats, view_lighting(options, viewmats)):
        image, mask, depth = render_view(primitives, viewmat, K, options.width, options.height, options.supersample,
                                         light, gain)
        stem = Path(name).stem
        image_bgr = cv2.cvtColor(np.round(image * 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
        for written, pixels in ((staging / "images" / name, image_bgr),
                                (staging / "masks" / name, (mask * 255).astype(np.uint8))):
            write_image(written, pixels)
        np.save(staging / "depths" / f"{stem}.npy", depth)
        rows, cols = np.nonzero(mask > 0.5)
        pick = rng.choice(len(rows), size=min(per_view, len(rows)), replace=False)
        rows, cols = rows[pick], cols[pick]
        camera = np.linalg.solve(K, np.stack([cols + 0.5, rows + 0.5, np.ones(len(rows))])) * depth[rows, cols]
        points.append((viewmat[:3, :3].T @ (camera - viewmat[:3, 3:4])).T)
        colors.append(np.round(image[rows, cols] * 255).astype(np.uint8))
    write_model(
        staging / "sparse" / "0", names, viewmats, np.tile(K, (options.views, 1, 1)), options.width, options.height,
        np.concatenate(points), np.concatenate(colors),
    )
    centers = camera_centers(torch.from_numpy(viewmats)).numpy()
    train = set()
    for size in DEFAULT_SPLIT_SIZES:
        if size < options.views:
            chosen = sorted(farthest_views(centers, size))
            train.update(chosen)
            (staging / f"sparse_{size}.txt").write_text("".join(f"{index}\n" for index in chosen))
    # Held-out views: about one in eight, never a training view of any split, at least two.
    held_out = [index for index in range(options.views) if index not in train]
    count = min(len(held_out), max(2, options.views // 8))
    test = [held_out[round(k * len(held_out) / count)] for k in range(count)]
    (staging / "sparse_test.txt").write_text("".join(f"{index}\n" for index in test))
    record = {"generator_version": GENERATOR_VERSION, "object_center": OBJECT_CENTER.tolist(), **asdict(options)}
    (staging / "synthetic.json").write_text(json.dumps(record, indent=2))


def default_cache_dir() -> Path:
    """`$WARPBAGS_CACHE`, else `$XDG_CACHE_HOME/warpbags`, else `~/.cache/warpbags`."""
    if os.environ.get("WARPBAGS_CACHE"):
        return Path(os.environ["WARPBAGS_CACHE"])
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "warpbags"


def ensure_synthetic_scene(options: SyntheticOptions = SyntheticOptions(),
                           cache_dir: str | os.PathLike | None = None) -> Path:
    """The cached synthetic scene folder for `options`, generated on first use.

    Safe for processes that ask for the same scene at once (benchmarks run side by side): each renders into its own
    staging folder, and one that finds the folder completed by another when it is done keeps that copy, which is
    the same scene (the folder name holds every generator setting).
    """
    folder = (Path(cache_dir) if cache_dir else default_cache_dir()) / options.folder_name()
    if (folder / "synthetic.json").is_file():
        return folder
    logging.getLogger("warpbags.data").warning("generating the synthetic scene into %s (first use)", folder)
    try:
        return generate_synthetic_scene(folder, options)
    except (OSError, WarpbagsError):
        if (folder / "synthetic.json").is_file():  # another process finished it first (the rename is atomic)
            return folder
        raise
