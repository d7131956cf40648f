"""warpbags: Bundle-Adjusting Gaussian Splatting (BAGS) with NVIDIA Warp kernels."""

from warpbags.errors import WarpbagsError
from warpbags.rendering import rasterization

__version__ = "0.1.0"

__all__ = ["WarpbagsError", "__version__", "rasterization"]
