"""crossline: a cross-line laser scanner on a measuring arm, from capture folders to accuracy reports."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("crossline")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"
