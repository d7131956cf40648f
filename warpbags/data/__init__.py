"""Scenes and datasets: loaders for the COLMAP/MipNeRF360, LLFF and transforms.json layouts, the synthetic scene."""

from warpbags.data.catalog import open_scene, resolve_scene
from warpbags.data.loaders import load_scene, object_center
from warpbags.data.scene import ORBIT_RADIUS, Scene, SceneNormalization, farthest_views
from warpbags.data.synthetic import SyntheticOptions, ensure_synthetic_scene, generate_synthetic_scene

__all__ = [
    "ORBIT_RADIUS",
    "Scene",
    "SceneNormalization",
    "SyntheticOptions",
    "ensure_synthetic_scene",
    "farthest_views",
    "generate_synthetic_scene",
    "load_scene",
    "object_center",
    "open_scene",
    "resolve_scene",
]
