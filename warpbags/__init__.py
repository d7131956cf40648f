"""warpbags: Bundle-Adjusting Gaussian Splatting (BAGS) with NVIDIA Warp kernels."""


def _source_checkout_roots() -> list[str]:
    """[the repository root] when this package runs from a source checkout, else [].

    kernels/, cli/ and configs/ sit at the top of the repository and install into this package (pyproject's
    package-dir). An installed warpbags has them inside; a checkout has them beside warpbags/, and whenever the
    checkout's root is on sys.path (the current directory of `python -c` run there) its warpbags/ shadows any
    install. Searching the root for this package's submodules then makes the checkout import as the install does.
    """
    from pathlib import Path  # noqa: PLC0415 - kept out of the package's namespace

    package = Path(__file__).resolve().parent
    root = package.parent
    if (root / "kernels" / "__init__.py").is_file() and not (package / "kernels").exists():
        return [str(root)]
    return []


__path__.extend(_source_checkout_roots())

from warpbags.errors import WarpbagsError  # noqa: E402 - needs the search path above
from warpbags.rendering import rasterization  # noqa: E402 - needs the search path above

__version__ = "0.1.0"

__all__ = ["WarpbagsError", "__version__", "rasterization"]
