"""How far a scene's reference poses are from an independent structure-from-motion run on all of its views.

    python bench/reference_poses.py SCENE [SCENE ...] [--json PATH]

SCENE: as bench/pose_recovery.py (a preset, a folder, `synthetic-small` or `synthetic-tele-small`). Every view of
the scene, as warpbags loads it (resolution, undistortion), is written out with its object mask, and pycolmap
reconstructs them: SIFT features inside the masks (the object only: maryrose's object was moved between capture
sequences, so its background does not hold still), exhaustive matching, incremental mapping, one SIMPLE_RADIAL
camera for all views. The reference poses are then compared with the reconstruction as the pose benches compare
an estimate: sim(3) Procrustes alignment of the camera centres, rotation error per view, centre error in % of the
orbit radius. Printed per scene: views registered, mean reprojection error (px), the reconstruction's focal length
and radial distortion next to the reference focal, the rotation error's mean / median / max over all views and
over each training split (sparse_4, sparse_6, sparse_9 where the scene has them), and the centre error. A scene
whose views SfM cannot reconstruct says so (the synthetic scenes: neither `synthetic`'s 48 views at 256 px nor
synthetic-tele-small's 16 at 128 px give SIFT enough to build a model).

What it is for: the pose benchmarks measure against the reference poses, so before a few-degree disagreement on a
real capture is blamed on the method, this says whether the reference itself holds to that precision. On maryrose
(NeRD's poses) all 69 views register and the reference sits 0.2 deg from the reconstruction on average.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import check_json, open_bench_scene, write_json  # noqa: E402
from warpbags.alignment import pose_errors  # noqa: E402
from warpbags.cli.common import clean_errors  # noqa: E402
from warpbags.data import ORBIT_RADIUS  # noqa: E402


def reconstruct(scene, folder: Path):
    """pycolmap's reconstruction of the scene's views (masked SIFT, exhaustive matching, incremental mapping), with
    the largest model's world-to-camera matrix per view name (views it did not register are absent); (None, {})
    when it builds no model."""
    import pycolmap  # noqa: PLC0415 - 57 MiB; only this bench and COLMAP scenes need it

    images, masks = folder / "images", folder / "masks"
    images.mkdir(parents=True)
    masks.mkdir()
    for index, name in enumerate(scene.image_names):
        stem = Path(name).name
        pixels = (scene.images[index].numpy() * 255).round().astype(np.uint8)
        cv2.imwrite(str(images / f"{stem}.png"), cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR))
        if scene.masks is not None:  # COLMAP's mask of image NAME is NAME.png, 0 = no features there
            cv2.imwrite(str(masks / f"{stem}.png.png"), (scene.masks[index].numpy() > 0.5).astype(np.uint8) * 255)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_RADIAL"
    if scene.masks is not None:
        reader.mask_path = str(masks)
    database = folder / "database.db"
    pycolmap.extract_features(database, images, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader)
    pycolmap.match_exhaustive(database)
    (folder / "sparse").mkdir()
    models = pycolmap.incremental_mapping(database, images, folder / "sparse")
    if not models:
        return None, {}
    model = max(models.values(), key=lambda m: m.num_reg_images())
    viewmats = {}
    for image in model.images.values():
        viewmat = np.eye(4)
        viewmat[:3] = image.cam_from_world().matrix()
        viewmats[Path(image.name).stem] = viewmat
    return model, viewmats


def compare(scene, model, viewmats: dict) -> dict:
    """The reference poses against the reconstruction (sim(3) Procrustes over the views it registered)."""
    names = [Path(name).name for name in scene.image_names]
    registered = [index for index, name in enumerate(names) if name in viewmats]
    estimate = torch.tensor(np.stack([viewmats[names[index]] for index in registered]))
    errors = pose_errors(estimate, scene.viewmats[registered].double(), alignment="procrustes")
    rotations = np.asarray(errors["rotation_errors_deg"], dtype=float)
    per_view = dict(zip(registered, rotations.tolist()))
    camera = next(iter(model.cameras.values()))
    splits = {}
    for key in ("4", "6", "9"):
        split = scene.splits.get(key, [])
        if split and all(index in per_view for index in split):
            splits[key] = [per_view[index] for index in split]
    return {
        "scene": scene.name, "views": len(names), "registered": len(registered),
        "reprojection_px": float(model.compute_mean_reprojection_error()),
        "sfm_focal": float(camera.params[0]), "sfm_radial": float(camera.params[3]),
        "reference_focal": float(scene.Ks[0, 0, 0]),
        "rotation_mean": float(rotations.mean()), "rotation_median": float(np.median(rotations)),
        "rotation_max": float(rotations.max()),
        "centres_pct": 100 * float(errors["translation_error_mean"]) / ORBIT_RADIUS,
        "splits": splits,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--json", type=Path, help="also write the rows here")
    args = parser.parse_args()
    torch.set_num_threads(1)
    check_json(args.json)
    scenes = {name: open_bench_scene(name) for name in args.scenes}  # a bad name fails before the first line
    rows = []
    for name, scene in scenes.items():
        started = time.time()
        with tempfile.TemporaryDirectory() as folder:
            model, viewmats = reconstruct(scene, Path(folder))
            if model is None or len(viewmats) < 3:
                print(f"{name}: structure from motion registered {len(viewmats)} of {scene.num_views} views (too few "
                      "matched features); nothing to compare", flush=True)
                continue
            row = compare(scene, model, viewmats)
        row["minutes"] = (time.time() - started) / 60
        rows.append(row)
        print(f"{name}: {row['registered']}/{row['views']} views registered, "
              f"reprojection {row['reprojection_px']:.2f} px, focal {row['sfm_focal']:.1f} "
              f"(reference {row['reference_focal']:.1f}), radial k {row['sfm_radial']:.4f}, {row['minutes']:.1f} min")
        print(f"  reference vs SfM, rotation deg: mean {row['rotation_mean']:.3f}, "
              f"median {row['rotation_median']:.3f}, max {row['rotation_max']:.3f}; "
              f"centres {row['centres_pct']:.2f}% of the orbit radius")
        for key, errors in row["splits"].items():
            print(f"  sparse_{key}: " + ", ".join(f"{error:.2f}" for error in errors))
    if args.json:
        write_json(args.json, rows)


if __name__ == "__main__":
    clean_errors(main)()  # a bad scene name: one line and exit code 2, as the CLI
