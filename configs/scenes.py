"""Named scenes: where each lives, its default resolution and published splits (typed presets, no logic).

`warpbags.data.catalog.open_scene` resolves a name (or any folder path) through these.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

MIPNERF360_URL = "http://storage.googleapis.com/gresearch/refraw360/360_v2.zip"
# maryrose's optics and framing for the synthetic object: an 18.6 deg field of view from 5.6 units, so the object
# fills 80-100% of the frame as in the real capture (`SyntheticOptions` fields).
TELEPHOTO_OPTICS: dict[str, float] = {"fov_deg": 18.6, "radius": 5.6}


@dataclass(frozen=True)
class ScenePreset:
    """One named scene.

    Attributes:
        name: the name users type (`warpbags info kitchen`).
        source: "data_root" (a folder under --data-root / $WARPBAGS_DATA / data/), "packaged" (shipped inside
            the warpbags package under `warpbags/assets/`) or "synthetic" (generated on first use into the cache).
        folders: candidate folder names, tried in order (relative to the data root or the package assets).
        resolution: image downsampling factor to load (images_{resolution}); None = the largest available.
        default_splits: splits used when the scene's own `sparse_{key}.txt` file is missing.
        how_to_get: one sentence telling a user how to obtain the data.
        synthetic: for source "synthetic", the generator's settings that differ from its defaults
            (`warpbags.data.synthetic.SyntheticOptions` fields).
    """

    name: str
    source: Literal["data_root", "packaged", "synthetic"]
    folders: tuple[str, ...] = ()
    resolution: int | None = None
    default_splits: dict[str, tuple[int, ...]] = field(default_factory=dict)
    how_to_get: str = ""
    synthetic: dict[str, Any] = field(default_factory=dict)


def _nerd_capture(repository: str) -> ScenePreset:
    """One of NeRD's real captures as its GitHub repository `vork/<repository>` is cloned (photographs, masks, LLFF
    poses), named in lower case and read at 1/8 as maryrose's images_8. Not shipped: they are CC BY-NC-SA."""
    return ScenePreset(
        name=repository.lower(),
        source="data_root",
        folders=(repository, repository.lower()),
        resolution=8,
        how_to_get=f"git clone https://github.com/vork/{repository} into a folder and pass that folder as "
                   "--data-root (or set WARPBAGS_DATA)",
    )


SCENES: dict[str, ScenePreset] = {
    preset.name: preset
    for preset in (
        ScenePreset(
            name="kitchen",
            source="data_root",
            folders=("kitchen", "360_v2/kitchen", "mip360/kitchen"),
            resolution=4,
            # GaussianObject's published 4-view kitchen split (maintainers, chensjtu/GaussianObject issue #10).
            default_splits={"4": (14, 70, 171, 196)},
            how_to_get=f"download {MIPNERF360_URL}, unzip it and pass its folder as --data-root (or set WARPBAGS_DATA)",
        ),
        ScenePreset(
            name="maryrose",
            source="packaged",
            folders=("maryrose",),
            resolution=8,
            how_to_get="it ships inside the warpbags package (warpbags/assets/maryrose); reinstall warpbags",
        ),
        # A second real capture from the NeRD datasets: the Mold Gold Cape (British Museum), gold and specular, 119
        # photographs of 3648 px with masks and NeRD's poses (LLFF), read at 1/8 (456 px).
        _nerd_capture("moldGoldCape"),
        # A third NeRD capture: the Ethiopian Head (British Museum), dark bronze, 66 photographs of 4000 px with masks
        # and NeRD's poses, a 29.7 deg field of view (maryrose: 18.6); read at 1/8 (500 px).
        _nerd_capture("ethiopianHead"),
        ScenePreset(
            name="synthetic",
            source="synthetic",
            how_to_get="it is generated on first use; set WARPBAGS_CACHE to a writable folder",
        ),
        # The synthetic object seen with maryrose's optics. Far from the object a camera's turn and a sideways shift
        # move the image almost alike, the hard case for pose recovery; exact ground truth still.
        ScenePreset(
            name="synthetic-tele",
            source="synthetic",
            how_to_get="it is generated on first use; set WARPBAGS_CACHE to a writable folder",
            synthetic=TELEPHOTO_OPTICS,
        ),
    )
}
