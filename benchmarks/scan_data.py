"""Benchmark scan data: frames with a real sensor's noise, and long scans made from them.

- :func:`sensor_capture` renders, with the simulator's own noise model, a plate scan on a
  2248x840 scan window whose sensor is noisier than the built-in presets' (read noise about
  1.4 DN, room light, PRNU, stronger speckle), so that its PNGs are the size of a real sensor's
  (~0.74 MB): the built-in renders (0.46 MB) are smoother than a real camera and flatter the
  decoder. Fixed seed; cached under benchmarks/.cache/.
- :func:`long_capture` makes a scan of any length from a rendered one: its frame files are
  hard-linked in a fixed-seed order (the laser pattern's phase kept), and each frame gets a
  pose of a long, varied arm path (a boustrophedon over the plate with slow tilt and height
  changes), so the points spread over a large surface as a real 20 000-50 000-frame scan's do.
  The images are reused, the geometry of each pose is not their own: the clouds are for
  throughput and memory, not accuracy.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

REPO = Path(__file__).resolve().parents[1]
CACHE = REPO / "benchmarks" / ".cache"
SCAN = "plate"

# the noisier sensor: electrons per DN are ~42 at 8 bit (full well 10500), so 60 e of read
# noise is ~1.4 DN, and 900 e of room light on white ~21 DN (its shot noise ~0.7 DN): the
# plate's background sits at ~22 DN with ~2 DN of noise, below the stripe threshold (38 DN)
SENSOR_NOISE = {"read_noise_e": 60.0, "prnu": 0.01}
AMBIENT_SCAN_E = 900.0
SPECKLE_CONTRAST = 0.25
WINDOW = (412, 604, 2248, 840)


def sensor_preset():
    """The paper's rig with a 2248x840 window and a real sensor's noise (see module doc)."""
    from crossline.sim.presets import PRESETS

    rig = PRESETS["paper"]
    sensor = dataclasses.replace(rig.sensor, scan_window=WINDOW, **SENSOR_NOISE)
    lasers = {k: dataclasses.replace(v, speckle_contrast=SPECKLE_CONTRAST) for k, v in rig.lasers.items()}
    return dataclasses.replace(rig, name="paper-sensor-noise", sensor=sensor, lasers=lasers,
                               ambient_scan_e=AMBIENT_SCAN_E)


def sensor_capture(frames: int = 240, seed: int = 7, pattern: str | None = None) -> Path:
    """A quick capture of the noisy-sensor rig with its plate scan of ``frames`` frames (cached);
    ``pattern`` (e.g. "AB": both lines in every frame) replaces the rig's laser pattern."""
    from crossline.sim import simulate

    tag = "" if pattern is None else "-" + pattern.replace(",", "")
    out = CACHE / f"sensor-{SCAN}-{frames}-s{seed}{tag}"
    if (out / "rig.yaml").is_file() and (out / "truth.json").is_file():
        return out
    shutil.rmtree(out, ignore_errors=True)
    simulate(out, preset=sensor_preset(), seed=seed, quick=True, frames=frames, scans=[SCAN],
             force=True, threads=2, progress=False,
             **({} if pattern is None else {"pattern": pattern.split(",")}))
    return out


def arm_path(n: int, seed: int = 0, rate_hz: float = 80.0) -> np.ndarray:
    """(n, 7) flange poses x, y, z, qw, qx, qy, qz of a long varied sweep (boustrophedon).

    Passes 400 mm long, 25 mm apart, at 30 mm/s; height and tilt wander slowly (a few mm,
    a few degrees) as a hand-guided or programmed arm's do.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    s = 30.0 * t  # mm along the path
    L, pitch = 400.0, 25.0
    k = np.floor(s / L)
    a = s - k * L
    x = np.where(k % 2 == 0, a, L - a) - L / 2 + 400.0
    y = -150.0 + pitch * k
    ph = rng.uniform(0, 2 * np.pi, 3)
    z = 350.0 + 4.0 * np.sin(2 * np.pi * t / 23.0 + ph[0])
    rx = np.deg2rad(3.0) * np.sin(2 * np.pi * t / 17.0 + ph[1])
    ry = np.deg2rad(3.0) * np.sin(2 * np.pi * t / 29.0 + ph[2])
    # small-angle rotation about x then y, composed as quaternions (tool pointing down: qx = 1)
    cx, sx = np.cos(rx / 2), np.sin(rx / 2)
    cy, sy = np.cos(ry / 2), np.sin(ry / 2)
    q1 = np.stack([cx * cy, sx * cy, cx * sy, -sx * sy], 1)
    down = np.array([0.0, 1.0, 0.0, 0.0])  # 180 deg about x
    w0, x0, y0, z0 = down
    w1, x1, y1, z1 = q1.T
    q = np.stack([w0 * w1 - x0 * x1 - y0 * y1 - z0 * z1, w0 * x1 + x0 * w1 + y0 * z1 - z0 * y1,
                  w0 * y1 - x0 * z1 + y0 * w1 + z0 * x1, w0 * z1 + x0 * y1 - y0 * x1 + z0 * w1], 1)
    return np.column_stack([x, y, z, q])


def long_capture(src: Path, n: int, seed: int = 0) -> Path:
    """A capture whose plate scan has ``n`` frames: ``src``'s frame files hard-linked in a
    fixed-seed order that keeps the laser pattern's phase, on the poses of :func:`arm_path`.

    Its calibration files are hard links to ``src``'s.
    """
    out = CACHE / f"{src.name}-long-{n}-s{seed}"
    if (out / "scans" / SCAN / "frames.csv").is_file():
        return out
    shutil.rmtree(out, ignore_errors=True)
    tmp = out.with_name(out.name + f".partial-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    rig = yaml.safe_load((src / "rig.yaml").read_text())
    rig["scans"] = {SCAN: rig["scans"][SCAN]}
    (tmp / "rig.yaml").write_text(yaml.safe_dump(rig, sort_keys=False))
    # hard links, not a symbolic link: a capture's files must lie inside its folder
    shutil.copytree(src / "calibration", tmp / "calibration", copy_function=os.link)
    table = pd.read_csv(src / "scans" / SCAN / "frames.csv", dtype={"lasers": str})
    states = table["lasers"].to_numpy()
    period = _pattern_period(states)
    rng = np.random.default_rng(seed)
    # frames of the same phase in the pattern are interchangeable: draw among them
    by_phase = [np.flatnonzero(np.arange(len(table)) % period == p) for p in range(period)]
    pick = np.array([rng.choice(by_phase[k % period]) for k in range(n)])
    rate = float(rig.get("frame_rate", 80.0))
    poses = arm_path(n, seed, rate)
    fdir = tmp / "scans" / SCAN / "frames"
    fdir.mkdir(parents=True)
    srcdir = src / "scans" / SCAN / "frames"
    for k, j in enumerate(pick):
        os.link(srcdir / f"{int(table['frame'].iloc[j]):06d}.png", fdir / f"{k:06d}.png")
    out_table = pd.DataFrame({"frame": np.arange(n), "time_s": np.round(np.arange(n) / rate, 6),
                              "lasers": states[pick]})
    for c, col in zip(("x", "y", "z", "qw", "qx", "qy", "qz"), poses.T, strict=True):
        out_table[c] = np.round(col, 6)
    out_table.to_csv(tmp / "scans" / SCAN / "frames.csv", index=False)
    os.rename(tmp, out)
    return out


def _pattern_period(states: np.ndarray) -> int:
    """Shortest period p with states[i] == states[i % p] for all i."""
    for p in range(1, len(states) + 1):
        if all(states[i] == states[i % p] for i in range(len(states))):
            return p
    return len(states)
