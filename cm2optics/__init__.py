"""cm2optics: design, simulate and reconstruct computational miniature mesoscopes (CM²)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("cm2optics")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+source"
