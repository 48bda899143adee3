"""ev3dgs: event-enhanced 3D Gaussian Splatting (simulator, DAVIS ingestion, trainer, exporters, viewer)."""
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("ev3dgs")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"

__all__ = ["__version__"]
