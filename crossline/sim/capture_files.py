"""The capture's own files besides its images, as a real rig writes them: rig.yaml and the CSV tables.

``_write_rig_yaml`` (rig.yaml in a fixed key order; a freeform's ``nominal_pose`` from
``_probed_datum``, its placement as the arm probes it), ``_write_csv`` (frames.csv and the
hand-eye poses.csv) with ``_fmt`` / ``_pose_row`` (``repr`` floats, poses as x, y, z, qw, qx,
qy, qz). Split from ``crossline.sim.capture`` (issue 21.3), which re-exports the names its
importers use.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml

from crossline.geometry import transform_to_pose
from crossline.io.atomic import atomic_path
from crossline.sim.capture_jobs import Output
from crossline.sim.presets import RigPreset

__all__ = ["DATUM_BASELINE_MM"]

DATUM_BASELINE_MM = 40.0  # how far apart the probed datum features of a part are


def _fmt(x: float) -> str:
    return repr(float(x))


def _pose_row(T: np.ndarray) -> list[str]:
    p, q = transform_to_pose(T)
    return [_fmt(v) for v in p] + [_fmt(v) for v in q]


def _write_csv(path: Path, header: list[str], rows: list[list[str]]) -> None:
    text = ",".join(header) + "\n" + "".join(",".join(r) + "\n" for r in rows)
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def _probed_datum(T_base_nominal: np.ndarray, rig: RigPreset,
                  rng: np.random.Generator) -> tuple[list[float], dict[str, Any]]:
    """A freeform's placement as ``nominal_pose`` (x, y, z, qw, qx, qy, qz), probed with the
    arm: off by the arm's per-axis error, and turned by it over the datums' baseline."""
    from crossline.geometry import make_transform, rotvec_to_matrix

    dt = rng.normal(0.0, rig.arm.sigma_axis_mm, 3)
    dr = rng.normal(0.0, rig.arm.sigma_axis_mm / DATUM_BASELINE_MM, 3)
    T = make_transform(rotvec_to_matrix(dr), dt) @ T_base_nominal
    p, q = transform_to_pose(T)
    error = {"translation_mm": dt.tolist(), "rotation_rad": dr.tolist(),
             "model": f"arm per-axis sigma {rig.arm.sigma_axis_mm:.4g} mm, turned by it over "
                      f"{DATUM_BASELINE_MM:g} mm"}
    return [round(float(v), 6) for v in (*p, *q)], error


def _write_rig_yaml(path: Path, rig: RigPreset, bits: int, scan_names: list[str],
                    output: Output = Output(), with_scans: bool = True,  # noqa: B008
                    datums: dict[str, list[float]] | None = None) -> None:
    s = rig.sensor
    x, y, w, h = s.scan_window
    scans = {}
    for spec in rig.scans:
        if spec.name not in scan_names:
            continue
        entry: dict[str, Any] = {"artefact": spec.artefact}
        if spec.artefact == "freeform":
            entry["nominal"] = f"{spec.name}.stl"
            if datums and spec.name in datums:
                entry["nominal_pose"] = datums[spec.name]
        if spec.artefact == "gauge_block":
            entry["height"] = float(spec.params["height"])
        if spec.artefact in ("sphere", "ball_bar"):
            entry["diameter"] = float(spec.params["diameter"])
        if spec.artefact == "ball_bar":
            entry["length"] = float(spec.params["length"])
        scans[spec.name] = entry
    sensor: dict[str, Any] = {"width": s.width, "height": s.height, "bit_depth": bits}
    if output.data_bits is not None:
        sensor["data_bits"] = output.data_bits
    if output.colour is not None:
        sensor["channel"] = output.colour
    data: dict[str, Any] = {
        "format": "crossline-capture/1",
        "description": f"simulated: {rig.description}",
        "capture_date": rig.capture_date,
        "simulated": True,
        "sensor": sensor,
    }
    if tuple(rig.lasers) != ("A", "B"):
        data["lasers"] = list(rig.lasers)
    data.update({
        "scan_window": {"x": x, "y": y, "width": w, "height": h},
        "frame_rate": float(s.frame_rate),
        "board": rig.board.board.to_dict(),
    })
    if with_scans:
        data["scans"] = scans
    text = yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=100)
    with atomic_path(path) as tmp:
        tmp.write_text(text)
