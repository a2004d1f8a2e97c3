"""crossline: a cross-line laser scanner on a measuring arm, from capture folders to accuracy reports.

The workflow (``snakemake``) and the ``crossline`` command run the stages; this package's top
level names the objects a user reads and writes from Python:

- :class:`Camera` (``camera.json``): intrinsics ``K`` (px), distortion ``(k1, k2, p1, p2,
  k3)``, sensor size; :meth:`Camera.project` maps camera-frame points (mm) to full-sensor
  pixels, :meth:`Camera.rays` pixels to unit rays in the camera frame.
- :class:`LaserPlanes` (``lasers.json``): each laser's plane ``n · p + d = 0`` in the camera
  frame (mm); ``planes["A"].intersect_rays(rays)`` triangulates (the paper's eq. 8).
- :class:`HandEye` (``handeye.json``): ``T_tool_cam`` (4×4, mm), the camera in the arm's
  flange frame; a point reaches the arm's base frame as ``T_base_tool @ T_tool_cam @ p_cam``.
- :class:`Board`: a calibration board as under ``board:`` in ``rig.yaml`` (points in mm).
- :func:`open_capture`, :func:`check_capture`: read a capture folder (``docs/DESIGN.md``);
  both raise :class:`CaptureError` listing every problem with its file and line.
- :func:`read_ply`: a fused cloud (``data/processed/<capture>/<scan>.ply``) as arrays by
  name: ``points`` (N, 3) in mm in the arm's base frame, ``normals``, ``laser``, ``frame``.
- :func:`read_e57`, :func:`write_e57`: clouds in ASTM E57 (mm here, metres in the file).
- :class:`CrosslineError`: base of every error caused by the input rather than by a bug.

Each name is imported on first use (PEP 562), so ``import crossline`` loads neither OpenCV
nor Open3D and the command line starts quickly. Example, on a capture the workflow has
calibrated (``data/interim/<capture>/calibration/``)::

    import numpy as np
    from crossline import Camera, HandEye, LaserPlanes

    cal = "data/interim/demo/calibration"
    camera = Camera.load(f"{cal}/camera.json")
    planes = LaserPlanes.load(f"{cal}/lasers.json")
    X = HandEye.load(f"{cal}/handeye.json").T_tool_cam      # T_tool_cam, 4x4, mm

    uv = np.array([[1500.0, 1000.0]])                        # full-sensor pixels (u, v)
    p_cam = planes["A"].intersect_rays(camera.rays(uv))      # where laser A lit it: (1, 3) mm
    back = camera.project(p_cam)                             # the pixel again, (1, 2)
    p_tool = (X @ np.append(p_cam[0], 1.0))[:3]              # the flange frame, mm
"""

from __future__ import annotations

from importlib import import_module
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING, Any

try:
    __version__ = version("crossline")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

# public name -> the module that defines it (imported when the name is first used)
_EXPORTS = {
    "Board": "crossline.board",
    "Camera": "crossline.camera",
    "CaptureError": "crossline.io.capture",
    "CrosslineError": "crossline.errors",
    "HandEye": "crossline.calibrate.handeye",
    "LaserPlanes": "crossline.laser",
    "check_capture": "crossline.io.capture",
    "open_capture": "crossline.io.capture",
    "read_e57": "crossline.io.clouds",
    "read_ply": "crossline.fuse",
    "write_e57": "crossline.io.clouds",
}

__all__ = [  # literal, for linters; tests/test_api.py checks it against _EXPORTS
    "Board",
    "Camera",
    "CaptureError",
    "CrosslineError",
    "HandEye",
    "LaserPlanes",
    "__version__",
    "check_capture",
    "open_capture",
    "read_e57",
    "read_ply",
    "write_e57",
]

if TYPE_CHECKING:  # for type checkers and IDEs; at run time __getattr__ imports on demand
    from crossline.board import Board
    from crossline.calibrate.handeye import HandEye
    from crossline.camera import Camera
    from crossline.errors import CrosslineError
    from crossline.fuse import read_ply
    from crossline.io.capture import CaptureError, check_capture, open_capture
    from crossline.io.clouds import read_e57, write_e57
    from crossline.laser import LaserPlanes


def __getattr__(name: str) -> Any:
    """Import a public name's module on first use and cache the name here (PEP 562)."""
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'crossline' has no attribute {name!r}")
    value = getattr(import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
