"""`warpbags view`: a viser web viewer of a run's Gaussians (rendered by warpbags) and its training cameras."""

from warpbags.viewer.content import TrainingCameras, ViewerContent, load_viewer_content
from warpbags.viewer.server import Viewer

__all__ = ["TrainingCameras", "Viewer", "ViewerContent", "load_viewer_content"]
