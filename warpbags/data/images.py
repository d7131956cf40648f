"""Images, masks and depth maps of a scene folder, read at one resolution, and their undistortion.

`images`, `images_2|4|8` (a missing downsampled folder is made from `images` in memory), `masks/` (same stem, png
or jpg, 255 or 1 = object; a file's alpha channel, or a palette PNG's index above 0, where it has one), depth maps
(`zoe_depth/*.png` 16-bit millimetres, or `depths/*.npy` in scene units).
Pixels are read as stored: an EXIF orientation is ignored, as COLMAP ignores it.
"""

from __future__ import annotations

import io
import math
import os
import re
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from warpbags.errors import WarpbagsError, one_line
from warpbags.files import read_array

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
JPEG_EXTENSIONS = (".jpg", ".jpeg")
FACTORS = (1, 2, 4, 8)
# What a scene read at its default factor may hold as float32 images and masks. A folder of full-size photographs
# (phone or DSLR) exceeds it: 119 images of 3648 x 3648 px take 25 GiB, so they are read at a reduced factor instead.
IMAGE_MEMORY_BUDGET = 2 * 1024**3
# Pixels are read as stored, an EXIF orientation ignored, as COLMAP reads them (its intrinsics and poses are of the
# stored pixels); OpenCV applies the orientation for every flag but IMREAD_UNCHANGED unless told not to.
_AS_STORED = cv2.IMREAD_IGNORE_ORIENTATION
# OpenCV's flags that have libjpeg decode a JPEG at 1/2, 1/4 or 1/8 of its size: (colour, grayscale).
JPEG_REDUCED_FLAGS = {2: (cv2.IMREAD_REDUCED_COLOR_2 | _AS_STORED, cv2.IMREAD_REDUCED_GRAYSCALE_2 | _AS_STORED),
                      4: (cv2.IMREAD_REDUCED_COLOR_4 | _AS_STORED, cv2.IMREAD_REDUCED_GRAYSCALE_4 | _AS_STORED),
                      8: (cv2.IMREAD_REDUCED_COLOR_8 | _AS_STORED, cv2.IMREAD_REDUCED_GRAYSCALE_8 | _AS_STORED)}


def default_resolution(root: Path) -> int:
    """1 if `images/` exists, else the first factor of `images_2|4|8/` that does."""
    if (root / "images").is_dir():
        return 1
    for factor in (2, 4, 8):
        if (root / f"images_{factor}").is_dir():
            return factor
    raise WarpbagsError(f"no image folder in {root}: expected images/ or images_2|4|8/")


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file, from its header alone."""
    try:
        with Image.open(path) as image:
            return image.size
    except FileNotFoundError:
        raise WarpbagsError(f"image {path} is missing (named by the camera file)") from None
    except OSError:
        raise WarpbagsError(f"image {path} is unreadable") from None


def scene_bytes(count: int, width: int, height: int, factor: int) -> int:
    """Bytes of `count` float32 RGB images and masks of width x height read at 1/`factor`."""
    return count * math.ceil(width / factor) * math.ceil(height / factor) * 4 * 4


def factor_within_budget(count: int, width: int, height: int, budget: int) -> int:
    """The finest of the factors 1, 2, 4, 8 at which `count` images of width x height fit `budget` (else 8)."""
    return next((factor for factor in FACTORS if scene_bytes(count, width, height, factor) <= budget), FACTORS[-1])


def physical_memory() -> int | None:
    """This machine's memory in bytes, where the OS tells it."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return None


def first_existing_image_dir(root: Path) -> Path:
    """The folder of `default_resolution`."""
    factor = default_resolution(root)
    return root / ("images" if factor == 1 else f"images_{factor}")


def resolution_path(root: Path, full_path: Path, resolution: int) -> Path:
    """The file to read for `full_path` at `resolution`: `images_{r}/...` if present, else the full-size one."""
    if resolution == 1:
        return full_path
    relative = full_path.relative_to(root)
    if relative.parts and relative.parts[0] == "images":
        downsampled = root.joinpath(f"images_{resolution}", *relative.parts[1:])
        if downsampled.is_file():
            return downsampled
        if downsampled.with_suffix(".png").is_file():  # some tools convert to png when downsampling
            return downsampled.with_suffix(".png")
    return full_path


def _decoded_reduced(path: Path, reduction: int) -> bool:
    """Whether libjpeg decodes `path` at 1/`reduction` itself: a JPEG, a reduction of 2, 4 or 8, and sides that it
    divides. Its reduced decode of other sides is ceil(size / reduction), the last row and column from fewer pixels,
    where the images and masks are round(size / reduction) of the whole: stretched to that, it put an edge up to 0.9 px
    from where the intrinsics see it. Those are decoded whole and resized."""
    if reduction not in JPEG_REDUCED_FLAGS or path.suffix.lower() not in JPEG_EXTENSIONS:
        return False
    width, height = image_size(path)
    return width % reduction == 0 and height % reduction == 0


# After a JPEG marker 0xFF: the bytes that do not end its entropy-coded scan data (a stuffed 0x00, the restart
# markers 0xD0-0xD7, fill bytes 0xFF)
_SCAN_END = re.compile(rb"\xff[^\x00\xd0-\xd7\xff]")


def _jpeg_cut_short(data: bytes) -> bool:
    """Whether the JPEG `data` ends before its end-of-image marker: its marker segments walked from the start (each
    skipped by its length, a scan's data to the next marker), so that what a camera appends after the picture (a
    motion photo's video) is never read. Data that is no JPEG, or breaks the layout, is left to the decoder."""
    if not data.startswith(b"\xff\xd8"):
        return False
    position = 2
    while position + 1 < len(data):
        if data[position] != 0xFF:
            return False  # not where a marker should be: corrupt, which the decoder reports
        marker = data[position + 1]
        if marker == 0xD9:  # end of image
            return False
        if marker == 0xFF or 0xD0 <= marker <= 0xD8 or marker == 0x01:  # fill byte, or a marker without a length
            position += 1 if marker == 0xFF else 2
            continue
        if position + 4 > len(data):
            return True
        position += 2 + int.from_bytes(data[position + 2:position + 4], "big")
        if marker == 0xDA:  # start of scan: its entropy-coded data runs to the next marker
            end = _SCAN_END.search(data, position)
            if end is None:
                return True
            position = end.start()
    return True


def _file_bytes(path: Path, what: str) -> bytes:
    """The bytes of the file at `path`, an image or a mask (`what`).

    Raises:
        WarpbagsError: the file cannot be read, or is a JPEG cut short (a copy or download that stopped): libjpeg
            decodes one, grey where its data ends, and only warns on stderr.
    """
    try:
        data = path.read_bytes()
    except OSError as error:
        raise WarpbagsError(f"{what} {path} is unreadable ({one_line(error)})") from None
    if path.suffix.lower() in JPEG_EXTENSIONS and _jpeg_cut_short(data):
        raise WarpbagsError(f"{what} {path} is cut short (its data ends inside the picture): copy it again")
    return data


def _decoded(path: Path, flag: int, what: str) -> np.ndarray | None:
    """OpenCV's decode of the file at `path` with `flag`, None where it cannot decode it (raises as `_file_bytes`)."""
    return cv2.imdecode(np.frombuffer(_file_bytes(path, what), dtype=np.uint8), flag)


def read_image(path: Path, reduction: int = 1) -> np.ndarray:
    """The image at `path` as float32 RGB(A) in [0, 1]; a JPEG is decoded at 1/`reduction` (2, 4 or 8) of its size
    by libjpeg's own scaling, 8x faster than a full decode for 1/8."""
    flag = JPEG_REDUCED_FLAGS[reduction][0] if _decoded_reduced(path, reduction) else cv2.IMREAD_UNCHANGED
    image = _decoded(path, flag, "image") if path.is_file() else None
    if image is None:
        if path.is_file():
            raise WarpbagsError(f"image {path} is unreadable")
        raise WarpbagsError(f"image {path} is missing (named by the camera file)")
    scale = 65535.0 if image.dtype == np.uint16 else 255.0
    image = image.astype(np.float32) / scale
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    channels = image.shape[2]
    if channels == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA)
    return cv2.cvtColor(image[:, :, :3], cv2.COLOR_BGR2RGB)


def read_images(
    files: list[Path], full_paths: list[Path], resolution: int, alpha_masks: bool = True
) -> tuple[np.ndarray, np.ndarray | None, int, int]:
    """Read all images; resize those read at full size to 1/resolution. Returns images, alphas, width, height.

    With `alpha_masks` (a scene without a mask folder) the images' alpha channels are their masks where they mark
    a background (`_masking_alphas`); without it, or where none does, the alphas are not kept (None).

    Raises:
        WarpbagsError: a missing or unreadable image, one of another size, or (with `alpha_masks`) an alpha
            channel that marks a background in some images only.
    """
    images = alphas = None
    width = height = 0
    has_alpha = []
    for index, (path, full_path) in enumerate(zip(files, full_paths)):
        reduction = resolution if path == full_path else 1  # a full-size file read for a downsampled folder
        image = read_image(path, reduction)
        if reduction > 1 and not _decoded_reduced(path, reduction):  # decoded whole
            full_height, full_width = image.shape[:2]
            image = cv2.resize(image, (round(full_width / reduction), round(full_height / reduction)),
                               interpolation=cv2.INTER_AREA)
        if images is None:
            height, width = image.shape[:2]
            images = np.empty((len(files), height, width, 3), dtype=np.float32)
        if image.shape[:2] != (height, width):
            raise WarpbagsError(
                f"image {path} is {image.shape[1]}x{image.shape[0]}, the others are {width}x{height}"
            )
        images[index] = image[:, :, :3]
        has_alpha.append(image.shape[2] == 4)
        if alpha_masks and has_alpha[-1]:
            if alphas is None:  # an image without an alpha channel is opaque everywhere
                alphas = np.ones((len(files), height, width), dtype=np.float32)
            alphas[index] = image[:, :, 3]
    if alphas is not None:
        alphas = _masking_alphas(alphas, files, has_alpha)
    return images, alphas, width, height


def _masking_alphas(alphas: np.ndarray, files: list[Path], has_alpha: list[bool]) -> np.ndarray | None:
    """The images' alpha channels `alphas` (1 for the images `files` where `has_alpha` is false), where they are the
    scene's masks: None where none marks a background (an alpha more than half opaque everywhere, as an RGBA export
    holds, says nothing of the object, as in a mask file), else `alphas`.

    Raises:
        WarpbagsError: some mark a background and an image has no alpha channel or one that marks none, named: its
            mask would be the whole frame.
    """
    marks_background = [not np.all(alpha > 0.5) for alpha in alphas]  # `masks_from_alphas`' object is > 0.5
    if not any(marks_background):
        return None
    if all(marks_background):
        return alphas
    silent, marking = marks_background.index(False), marks_background.index(True)
    height, width = alphas.shape[1:]
    if not has_alpha[silent]:
        raise WarpbagsError(f"image {files[silent]} has no alpha channel, {files[marking]}'s cuts its object out: "
                            "give every image one or none (masks/ holds masks otherwise)")
    raise WarpbagsError(f"image {files[silent]}'s alpha channel is opaque everywhere at {width}x{height} (more than "
                        f"half), which says nothing of its object, where {files[marking]}'s cuts its object out: cut "
                        "out every image's object, or none (masks/ holds masks otherwise)")


def _shared_stems(names: list[str]) -> set[str]:
    """The file stems that more than one of the images `names` has (view_0 of cam0/view_0.JPG and cam1/view_0.JPG)."""
    counts = Counter(Path(name).stem for name in names)
    return {stem for stem, count in counts.items() if count > 1}


def _find_by_stem(folder: Path, name: str, extensions: tuple[str, ...], stem_shared: bool) -> Path | None:
    """`folder/<stem><ext>`, trying the name with its sub-folders, then the bare file name (transforms.json
    names such as images/frame_001.png look up masks/frame_001.png), then `<name><ext>` (frame_001.png.png).

    The bare file name is not tried where another image has the same stem (`stem_shared`: cam0/view_0.JPG and
    cam1/view_0.JPG): masks/view_0.png would be taken for both, one of them another view's."""
    relative = Path(name)
    bare = () if stem_shared else (Path(relative.stem),)
    for stem in (relative.with_suffix(""), *bare, relative):  # the most specific first
        path = _with_extension(folder, stem, extensions)
        if path is not None:
            return path
    return None


def _with_extension(folder: Path, stem: Path, extensions: tuple[str, ...]) -> Path | None:
    """`folder/<stem><ext>` for the first of `extensions` that exists, whatever the case of its extension: tools
    that save masks as view.Png or depth maps as view.NPY are common, and on a case-sensitive file system only the
    listed spellings would be found."""
    for extension in extensions:
        candidate = folder / f"{stem}{extension}"
        if candidate.is_file():
            return candidate
    directory = (folder / stem).parent
    if not directory.is_dir():
        return None
    found = {}
    for entry in sorted(directory.iterdir()):
        name, suffix = entry.name[:len(stem.name)], entry.name[len(stem.name):]
        if name == stem.name and entry.is_file():
            found.setdefault(suffix.lower(), entry)
    return next((found[extension.lower()] for extension in extensions if extension.lower() in found), None)


def _missing(what: str, folder: Path, name: str, extensions: str, stem_shared: bool) -> WarpbagsError:
    """The error for the missing `what` (a mask, a depth map) of image `name`: the file expected, with the image's
    sub-folders where its stem is shared (`_find_by_stem` then looks the bare name up for none of those images)."""
    relative = Path(name)
    if not stem_shared:
        return WarpbagsError(f"{what} for image {name} is missing: expected {folder / relative.stem}{extensions}")
    return WarpbagsError(f"{what} for image {name} is missing: expected {folder / relative.with_suffix('')}"
                         f"{extensions} (images in other folders are named {relative.stem} too, so a file named "
                         f"{relative.stem} is taken for none of them)")


def _require_size(found_width: int, found_height: int, width: int, height: int, path: Path, what: str) -> None:
    """Accept a `what` (a mask, a depth map) of found_width x found_height for an image of width x height: the same
    size, an integer multiple of it (another resolution) or a full size that a downsampled read rounds to it
    (`read_images`: 33 px read at 1/2 is 16 px).

    Raises:
        WarpbagsError: any other size, named with the file's.
    """
    if (found_width, found_height) == (width, height):
        return
    factor_x, factor_y = found_width / width, found_height / height
    same_aspect = abs(factor_x - factor_y) <= 0.02 * factor_x and factor_x >= 1.0
    rounded = any((round(found_width / factor), round(found_height / factor)) == (width, height)
                  for factor in FACTORS[1:])
    if not rounded and (not same_aspect or abs(factor_x - round(factor_x)) > 0.02):
        raise WarpbagsError(f"{what} {path} is {found_width}x{found_height}, its image is {width}x{height}")


def _resize_to(array: np.ndarray, width: int, height: int, path: Path, what: str, nearest: bool) -> np.ndarray:
    """`array` at (width, height), resized from a size `_require_size` accepts (else it raises)."""
    found_height, found_width = array.shape[:2]
    _require_size(found_width, found_height, width, height, path, what)
    if (found_width, found_height) == (width, height):
        return array
    interpolation = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA
    return cv2.resize(array, (width, height), interpolation=interpolation)


def _read_mask(path: Path, width: int, height: int) -> tuple[np.ndarray, str]:
    """The mask file at `path`, for an image of `width` x `height`, as float32 levels in [0, 1], half and above the
    object, and what it holds where it holds no object (for the error). The levels are, in turn: its alpha channel
    where that marks a background (some pixel under half opaque) and its colour where opaque is not a
    black-and-white mask itself (`_two_level`): an RGBA cutout of the photograph, a silhouette on transparency (an
    alpha opaque everywhere, as editors save one, or a black and white mask on a transparent canvas is read by its
    colour, the transparent pixels background whatever their colour); the indices of a palette PNG whose index 0 is
    black and whose colours are not all greys (DAVIS and VOC style: index 1, coloured (128, 0, 0), is the object);
    else its grey levels (`_grey_levels`). A JPEG at 2, 4 or 8 times `width` is decoded at that reduction.

    Raises:
        WarpbagsError: the file cannot be read or decoded, or is a JPEG of a size `_require_size` refuses.
    """
    if path.suffix.lower() in JPEG_EXTENSIONS:  # no alpha channel nor palette
        full_width, full_height = image_size(path)
        # held to the rules of any mask's size before a reduced decode, which would pass 130 px at 1/2 as 65 px for
        # a 64 px image (where a 130 px PNG is refused) and name its reduced size for one of a wrong size
        _require_size(full_width, full_height, width, height, path, "mask")
        reduction = round(full_width / width)
        # a mask `_decoded_reduced` refuses is decoded whole and resized as the images are (`_resize_to`)
        reduced = _decoded_reduced(path, reduction)
        mask = _decoded(path, JPEG_REDUCED_FLAGS[reduction][1] if reduced else
                        cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH | _AS_STORED, "mask")
        if mask is None:
            raise WarpbagsError(f"mask {path} is unreadable")
        return _grey_levels(mask)
    data = _file_bytes(path, "mask")
    mask = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if mask is None:
        raise WarpbagsError(f"mask {path} is unreadable")
    grey = cv2.cvtColor(mask[..., :3], cv2.COLOR_BGR2GRAY) if mask.ndim == 3 else mask
    if mask.ndim == 3 and mask.shape[2] == 4:
        alpha, scale = mask[..., 3], np.iinfo(mask.dtype).max
        if alpha.min() < scale / 2:
            # the colour of a transparent pixel is not drawn (editors keep any there, white as often as black): a
            # black object on a transparent white canvas read by its colour was its background
            opaque = alpha >= scale / 2
            if not _two_level(grey[opaque]):
                return alpha.astype(np.float32) / scale, (f"its alpha channel, the mask in a file with one, is at "
                                                          f"most {alpha.max()} of {scale}; more than half opaque "
                                                          "marks the object")
            grey = np.where(opaque, grey, 0).astype(grey.dtype)
    indices = _palette_indices(data, path)
    if indices is not None:
        return (indices > 0).astype(np.float32), "index 0 everywhere; in a palette PNG an index above 0 marks it"
    return _grey_levels(grey, in_colour=mask.ndim == 3 and bool(np.any(mask[..., :3] != mask[..., :1])))


def _palette_indices(data: bytes, path: Path) -> np.ndarray | None:
    """The indices of the palette PNG `data` where it is a label image (DAVIS, VOC: index 0 black, colours in its
    palette; or indices past its palette); None for any other file, and for a palette of greys or one whose index 0
    is not black (a grey or a quantized colour mask stored with a palette, which may list its object first: read by
    its colour).

    Raises:
        WarpbagsError: a palette PNG that PIL cannot decode.
    """
    try:
        with Image.open(io.BytesIO(data)) as image:
            if image.mode != "P":
                return None
            indices = np.asarray(image)
            colours = np.asarray(image.getpalette(), dtype=np.int64).reshape(-1, 3)
    except OSError as error:
        raise WarpbagsError(f"mask {path} is unreadable ({one_line(error)})") from None
    used = np.unique(indices)
    listed = used[used < len(colours)]
    if len(listed) < len(used):  # PIL saves a label image without colours; OpenCV reads its indices as black
        return indices
    if colours[0].any() or np.all(colours == colours[:, :1]):
        return None
    return indices


def _two_level(grey: np.ndarray) -> bool:
    """Whether grey levels are a black-and-white picture (a mask drawn in colour): black and white pixels both,
    and at most 2% of them between 10% and 90% of full scale, where an antialiased edge puts a mask's few (a
    photograph has many; one colour everywhere is no mask)."""
    scale = np.iinfo(grey.dtype).max
    dark, bright = grey <= 0.1 * scale, grey >= 0.9 * scale
    return bool(dark.any() and bright.any() and grey.size - np.count_nonzero(dark | bright) <= 0.02 * grey.size)


def _grey_levels(mask: np.ndarray, in_colour: bool = False) -> tuple[np.ndarray, str]:
    """A grey mask's levels in [0, 1], and what it holds where it holds no object (`_read_mask`). The full scale is
    the least of 1, 255 and 65535 that its values reach up to: a 0 / 1 mask (as some segmentation tools save them),
    0 / 255 also in a 16-bit file, 0 / 65535. `in_colour`: `mask` is the grey of a file in colour, said in the
    error, as a label image saved in colour (VOC's object (128, 0, 0) is grey 38) holds no object by its grey, and
    which colour labels the object is not guessed."""
    top = int(mask.max())
    scale = next(level for level in (1, 255, 65535) if top <= level)
    marks = "65535, 255 or 1" if mask.dtype == np.uint16 else "255 or 1"
    holds = "0 everywhere" if top == 0 else f"its values are at most {top}, under half of {scale}"
    if in_colour:
        return mask.astype(np.float32) / scale, (f"it is in colour (its channels differ) and read as grey {holds}; a "
                                                 f"mask is grey: 0 around the object, {marks} on it")
    return mask.astype(np.float32) / scale, f"{holds}; {marks} marks the object"


def mask_folder(root: Path, resolution: int) -> Path | None:
    """The scene's mask folder: `masks_{resolution}/`, else `masks/`; None without either.

    Raises:
        WarpbagsError: neither, but a `masks_{factor}/` of another resolution, whose masks are of that resolution
            alone: read at this one, the scene had no masks, silently.
    """
    for folder in (root / f"masks_{resolution}", root / "masks"):
        if folder.is_dir():
            return folder
    others = [factor for factor in FACTORS if factor != resolution and (root / f"masks_{factor}").is_dir()]
    if others:
        found = ", ".join(f"masks_{factor}/ (for --resolution {factor})" for factor in others)
        raise WarpbagsError(f"no masks/ or masks_{resolution}/ folder in {root} for resolution {resolution}, only "
                            f"{found}: read the scene at a resolution that has masks, or add masks/ (full-size "
                            "masks serve every resolution)")
    return None


def read_masks(root: Path, names: list[str], width: int, height: int, resolution: int) -> np.ndarray | None:
    """[C,H,W] float32 0/1 masks from `masks_{resolution}/` or `masks/`, or None without a mask folder. A mask file
    holds 0 / 255 (or grey levels, thresholded at half; 0 / 65535 in 16 bits) or, as some segmentation tools save
    them, 0 / 1; or the object as its alpha channel, or as the indices above 0 of a palette PNG (`_read_mask`).

    Raises:
        WarpbagsError: a mask missing, unreadable, of another size than its image, or without any object pixel; or
            a mask folder of another resolution only (`mask_folder`).
    """
    folder = mask_folder(root, resolution)
    if folder is None:
        return None
    shared_stems = _shared_stems(names)
    masks = np.empty((len(names), height, width), dtype=np.float32)
    for index, name in enumerate(names):
        stem_shared = Path(name).stem in shared_stems
        path = _find_by_stem(folder, name, IMAGE_EXTENSIONS, stem_shared)
        if path is None:
            raise _missing("mask", folder, name, ".png or .jpg", stem_shared)
        levels, holds = _read_mask(path, width, height)
        masks[index] = _resize_to(levels, width, height, path, "mask", nearest=False) >= 0.5
        if not masks[index].any() and np.any(levels >= 0.5):
            raise WarpbagsError(f"mask {path} holds no object pixel at {width}x{height} (its object is smaller than "
                                "a pixel there)")
        if not masks[index].any():
            raise WarpbagsError(f"mask {path} holds no object pixel ({holds})")
    return masks


def masks_from_alphas(alphas: np.ndarray, files: list[Path]) -> np.ndarray:
    """[C,H,W] float32 0/1 masks from the alpha channels of the images `files` (a scene without a mask folder):
    more than half opaque is the object.

    Raises:
        WarpbagsError: an alpha channel without any object pixel, as `read_masks` refuses an empty mask file.
    """
    masks = (alphas > 0.5).astype(np.float32)
    for path, alpha, mask in zip(files, alphas, masks):
        if not mask.any():
            # the alphas as read, at the scene's resolution: an object pixel of the file may be a fraction of one
            opacity = "transparent everywhere" if alpha.max() == 0 else f"at most {alpha.max():.0%} opaque"
            raise WarpbagsError(f"image {path} holds no object pixel at {alpha.shape[1]}x{alpha.shape[0]} (its alpha "
                                f"channel, the mask without a masks/ folder, is {opacity} there; more than half "
                                "opaque marks the object)")
    return masks


def read_depths(root: Path, names: list[str], width: int, height: int) -> tuple[np.ndarray | None, str | None]:
    """`depths/*.npy` (scene units) or `zoe_depth/*.png` (16-bit millimetres, monocular: relative).

    Raises:
        WarpbagsError: a depth map missing, of another shape or size than its image, or a `zoe_depth` PNG that is
            not single-channel 16-bit.
    """
    shared_stems = _shared_stems(names)
    for folder, extension, units in ((root / "depths", ".npy", "scene"), (root / "zoe_depth", ".png", "relative")):
        if not folder.is_dir():
            continue
        depths = np.empty((len(names), height, width), dtype=np.float32)
        for index, name in enumerate(names):
            stem_shared = Path(name).stem in shared_stems
            path = _find_by_stem(folder, name, (extension,), stem_shared)
            if path is None:
                raise _missing("depth map", folder, name, extension, stem_shared)
            if extension == ".npy":
                depth = read_array(path, "depth map").astype(np.float32)
            else:
                raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
                # an 8-bit PNG is a picture of the depths (estimators save one beside the map): its levels are no
                # millimetres
                if raw is None or raw.ndim != 2 or raw.dtype != np.uint16:
                    raise WarpbagsError(f"depth map {path} is not a single-channel 16-bit PNG")
                depth = raw.astype(np.float32) / 1000.0
            depth = np.squeeze(depth)
            if depth.ndim != 2:
                raise WarpbagsError(f"depth map {path} has shape {depth.shape}, expected [H,W]")
            depths[index] = _resize_to(depth, width, height, path, "depth map", nearest=True)
        return depths, units
    return None, None


def undistort(
    images: np.ndarray, masks: np.ndarray | None, depths: np.ndarray | None, Ks: np.ndarray, distortions: np.ndarray
) -> None:
    """Undistort in place to the same pinhole K (OpenCV's pixel centres are at integers: shift by 0.5)."""
    height, width = images.shape[1:3]
    for index in range(len(images)):
        if not np.any(distortions[index]):
            continue
        K_opencv = Ks[index].copy()
        K_opencv[:2, 2] -= 0.5
        map_x, map_y = cv2.initUndistortRectifyMap(
            K_opencv, distortions[index], None, K_opencv, (width, height), cv2.CV_32FC1
        )
        images[index] = cv2.remap(images[index], map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        if masks is not None:
            masks[index] = cv2.remap(masks[index], map_x, map_y, cv2.INTER_NEAREST)
        if depths is not None:
            depths[index] = cv2.remap(depths[index], map_x, map_y, cv2.INTER_NEAREST)
