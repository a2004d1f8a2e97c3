"""A rendered capture's true calibration as the calibration stages' artefacts.

Scoring a later stage against the truth needs the calibration out of the way: written from
``truth.json`` in the stages' own formats, the true camera, laser planes and hand-eye matrix
go into the scan stages exactly as estimated ones would, so what is left is extraction.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from crossline.camera import Camera
from crossline.io.atomic import write_json
from crossline.io.capture import open_capture
from crossline.laser import LaserPlanes

__all__ = ["write_true_calibration"]


def write_true_calibration(capture: str | Path, dest: str | Path) -> tuple[Path, Path, Path]:
    """camera.json, lasers.json and handeye.json in ``dest`` from the capture's truth.json."""
    capture, dest = Path(capture), Path(dest)
    truth = json.loads((capture / "truth.json").read_text())
    sensor = open_capture(capture).rig.sensor
    dest.mkdir(parents=True, exist_ok=True)
    Camera(np.array(truth["camera"]["K"]), np.array(truth["camera"]["dist"]),
           (sensor.width, sensor.height)).save(dest / "camera.json")
    LaserPlanes.from_dict(truth["lasers"]).save(dest / "lasers.json")
    write_json(dest / "handeye.json", {"T_tool_cam": truth["T_tool_cam"], "method": "truth"})
    return dest / "camera.json", dest / "lasers.json", dest / "handeye.json"
