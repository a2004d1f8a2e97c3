"""Laser-plane calibration against the virtual rig's truth, with and without the albedo gain.

Renders (or reuses) the camera and laser-plane views of quick captures of several rigs: the
two built-in presets, the paper rig with an asymmetric light-circle board, and random rigs
(by default random-small seeds 1 and 2: light circles on 4 mm, a chessboard of 1.25 mm
squares). For each laser, the stage's own ``stripe_points`` and ``robust_plane`` run on
every pose with the TRUE camera (to isolate the stage), once with the board's albedo taken
out of the stripe (the default) and once without; printed per laser: the plane's angle to
the true plane, its offset, each pose's centres and the median / robust sigma of their
distances to the true plane, and the albedo ratio and black level the gain found.

    python benchmarks/bench_laser_planes.py                 # results/laser_planes.{txt,json}
    python benchmarks/bench_laser_planes.py --margin-px 2
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
CACHE = HERE / ".cache" / "laser_planes"
RESULTS = HERE / "results"

RIGS = {
    "paper": ["--preset", "paper", "--seed", "0"],
    "compact": ["--preset", "compact", "--seed", "0"],
    "paper-light-asym": ["--preset", "paper", "--seed", "0", "--board", "asymmetric:7x13:2.5:1.5:light"],
    "random-small-1": ["--preset", "random-small", "--seed", "1"],
    "random-small-2": ["--preset", "random-small", "--seed", "2"],
}


def render(name: str, args: list[str]) -> Path:
    """The rig's quick capture, camera and laser views only (cached)."""
    out = CACHE / name
    if not (out / "rig.yaml").is_file():
        shutil.rmtree(out, ignore_errors=True)
        subprocess.run(["crossline", "simulate", str(out), *args, "--quick", "--parts",
                        "camera,lasers", "--threads", "2"], check=True, capture_output=True)
    return out


def measure(capture: Path, margin_px: float) -> list[dict]:
    """One row per laser and variant: plane error against truth and the poses' figures."""
    from crossline.calibrate.lasers import _read_pose_images, robust_plane, stripe_points
    from crossline.camera import Camera
    from crossline.errors import CrosslineError
    from crossline.geometry import angle_between
    from crossline.io.capture import open_capture
    from crossline.robust import robust_sigma

    cap = open_capture(capture)
    truth = json.loads((capture / "truth.json").read_text())
    tc = truth["camera"]
    cam = Camera(np.asarray(tc["K"]), np.asarray(tc["dist"]), (cap.rig.sensor.width, cap.rig.sensor.height))
    shape = (cap.rig.sensor.height, cap.rig.sensor.width)
    rows = []
    for laser, views in sorted(cap.laser_views.items()):
        n_t, d_t = np.asarray(truth["lasers"][laser]["normal"]), float(truth["lasers"][laser]["d"])
        images = [(v.pose, _read_pose_images(v, shape, cap.rig.sensor.channel)) for v in views]
        for variant, gain in (("without gain", False), ("albedo gain", True)):
            pts, groups, noise, poses = [], [], [], []
            for i, (pose, (b, la, det)) in enumerate(images):
                try:
                    s = stripe_points(cam, cap.rig.board, b, la, name=pose, detect_image=det,
                                      margin_px=margin_px, normalise_albedo=gain)
                except CrosslineError:
                    poses.append({"pose": pose, "usable": False})
                    continue
                r = s.points @ n_t + d_t
                med = float(np.median(r))
                poses.append({"pose": pose, "usable": True, "centres": len(r), "median_um": 1e3 * med,
                              "sigma_um": 1e3 * robust_sigma(r),
                              "albedo": s.albedo})
                pts.append(s.points)
                groups.append(np.full(len(r), i))
                noise.append(2 * i + s.on_other)
            row = {"rig": capture.name, "laser": laser, "variant": variant, "poses": poses,
                   "angle_deg": None, "d_error_um": None}
            if len(pts) >= 2:
                # as the stage fits: poses as groups, each pose and albedo class with its noise
                n, d, _ = robust_plane(np.concatenate(pts), groups=np.concatenate(groups),
                                       noise_groups=np.concatenate(noise))
                if n @ n_t < 0:
                    n, d = -n, -d
                row["angle_deg"] = float(np.degrees(angle_between(n, n_t)))
                row["d_error_um"] = 1e3 * (d - d_t)
            rows.append(row)
    return rows


def fmt_row(r: dict) -> str:
    ang = "no plane (fewer than 2 usable poses)" if r["angle_deg"] is None else \
        f"{r['angle_deg']:.4f} deg, d {r['d_error_um']:+.1f} um"
    poses = " ".join(f"{p['pose']}:{p['centres']}/{p['median_um']:+.1f}/{p['sigma_um']:.1f}"
                     if p["usable"] else f"{p['pose']}:unusable" for p in r["poses"])
    black = [p["albedo"]["black_level"] for p in r["poses"] if p.get("albedo")]
    extra = f"  black level {min(black):.0f}-{max(black):.0f}" if black else ""
    return f"{r['rig']:18s} {r['laser']} {r['variant']:13s} {ang:38s} {poses}{extra}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--margin-px", type=float, default=4.0, help="lasers.margin_px (default 4)")
    ap.add_argument("--rigs", default=",".join(RIGS), help="comma-separated among " + ", ".join(RIGS))
    a = ap.parse_args(argv)
    rows = []
    for name in a.rigs.split(","):
        rows += measure(render(name, RIGS[name]), a.margin_px)
        for r in rows[-4:]:
            print(fmt_row(r), flush=True)
    head = [f"laser planes against truth (true camera, margin_px {a.margin_px:g}), quick captures;",
            "poses: pose:centres/median um/robust sigma um of their distances to the true plane"]
    text = "\n".join(head + [fmt_row(r) for r in rows])
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "laser_planes.txt").write_text(text + "\n")
    (RESULTS / "laser_planes.json").write_text(json.dumps(rows, indent=1) + "\n")
    print(f"wrote {RESULTS / 'laser_planes.txt'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
