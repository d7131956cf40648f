"""View splits of a scene folder: `sparse_{4,6,9,test}.txt`, else published, farthest-point or every-8th views."""

from __future__ import annotations

import logging
from collections.abc import Collection
from pathlib import Path

from warpbags.data.scene import DEFAULT_SPLIT_SIZES, Scene, farthest_views
from warpbags.errors import WarpbagsError

logger = logging.getLogger("warpbags.data")

TEST_EVERY = 8
"""Without `sparse_test.txt`, every 8th view not used for training is a test view (the MipNeRF360 hold-out)."""


def read_split_file(path: Path, num_views: int) -> list[int]:
    """0-based view indices, one per line (blank lines ignored), in UTF-8 text with or without the byte-order mark
    Notepad writes.

    Raises:
        WarpbagsError: text of another encoding (PowerShell's `>` writes UTF-16), a line that is no view index, or
            an index out of range.
    """
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise WarpbagsError(f"{path} is not UTF-8 text (PowerShell's > writes UTF-16): save it as UTF-8, one view "
                            "index a line") from None
    indices = []
    for line_number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        try:
            index = int(line.strip())
        except ValueError:
            raise WarpbagsError(f"{path}:{line_number}: {line.strip()!r} is not a view index") from None
        if not 0 <= index < num_views:
            raise WarpbagsError(f"{path}:{line_number}: view index {index} out of range for {num_views} images")
        indices.append(index)
    return indices


def read_splits(
    root: Path, scene: Scene, default_splits: dict[str, list[int]] | None, test_names: set[str] | None
) -> tuple[dict[str, list[int]], dict[str, str]]:
    """The scene's splits (key -> view indices) and where each came from (key -> file name or rule)."""
    splits, sources = {}, {}
    for path in sorted(root.glob("sparse_*.txt")):
        key = path.stem.removeprefix("sparse_")
        splits[key], sources[key] = read_split_file(path, scene.num_views), path.name
        if key.isdigit() and not len(set(splits[key])) == len(splits[key]) == int(key):
            raise WarpbagsError(f"{path}: a split of {key} views needs {key} different view indices, got "
                                f"{splits[key]}")
    if "test" not in splits and test_names:
        splits["test"] = [i for i, name in enumerate(scene.image_names) if name in test_names]
        sources["test"] = "transforms_test.json"
    for key, indices in (default_splits or {}).items():
        if key in splits:
            continue
        bad = [index for index in indices if not 0 <= index < scene.num_views]
        if bad:
            raise WarpbagsError(
                f"split {key} of scene {scene.name}: view index {bad[0]} out of range for {scene.num_views} images"
            )
        splits[key], sources[key] = list(indices), "preset"
        logger.warning("%s: sparse_%s.txt missing, using the published split %s", scene.name, key, indices)
    # training views are chosen among the views that are not held out for testing, the files' and the presets' alike
    test = set(splits.get("test", []))
    for key, indices in splits.items():
        if key != "test" and test & set(indices):
            raise WarpbagsError(f"split {key} of scene {scene.name} ({sources[key]}) uses test views "
                                f"{sorted(test & set(indices))}")
    centers = scene.camera_centers().double().numpy()
    for size in DEFAULT_SPLIT_SIZES:
        if str(size) in splits or size > scene.num_views - len(test):
            continue
        splits[str(size)] = sorted(farthest_views(centers, size, excluded=test))
        sources[str(size)] = "farthest-point"
        logger.warning("%s: sparse_%d.txt missing, farthest-point views %s", scene.name, size, splits[str(size)])
    if "test" not in splits:
        train = {index for key, indices in splits.items() for index in indices}
        splits["test"] = [i for i in range(0, scene.num_views, TEST_EVERY) if i not in train]
        sources["test"] = f"every {TEST_EVERY}th"
        logger.warning("%s: sparse_test.txt missing, test views %s", scene.name, splits["test"])
    return splits, sources


def evaluation_views(scene: Scene, training_names: Collection[str]) -> list[int]:
    """The views a run that trained on the views named `training_names` is evaluated on: the scene's test split,
    or, where the every-8th rule left that empty (a capture of few views, whose splits take every 8th view), every
    8th view the run did not train on.

    Raises:
        WarpbagsError: there are none, or the test split holds a view the run trained on (a sparse_test.txt
            written after training).
    """
    test, source = scene.splits.get("test", []), scene.split_sources.get("test", "")
    trained = [scene.image_names[i] for i in test if scene.image_names[i] in training_names]
    if trained:
        raise WarpbagsError(f"{scene.root}: its test split ({source}) holds views the run trained on: "
                            f"{', '.join(trained)}")
    if not test and source == f"every {TEST_EVERY}th":
        test = [i for i in range(0, scene.num_views, TEST_EVERY) if scene.image_names[i] not in training_names]
        if test:  # runs of other view counts may be evaluated on other views: said where eval's warnings are
            logger.warning("%s: every %dth view is in a training split; this run is evaluated on those it did not "
                           "train on, %s", scene.name, TEST_EVERY, test)
    if not test:
        raise WarpbagsError(f"{scene.root} has no test split (sparse_test.txt)"
                            + (f": without the file every {TEST_EVERY}th view is held out, and all of those are "
                               "training views" if source == f"every {TEST_EVERY}th" else ""))
    return list(test)
