"""Write a simulated capture folder (DESIGN.md §2) with its truth, in parallel and atomically.

Every image is rendered with its own random generator seeded from ``(seed, kind, index)``, so
the files do not depend on the number of worker processes (which also run BLAS and OpenCV
on one thread, like a render in one process); PNGs are written with a fixed row filter, zlib
level and strategy, CSVs with ``repr`` floats, JSON and YAML in a fixed key order, so the
same seed gives byte-identical files.

Options make the captures real rigs write (see ``simulate``): a one-laser rig, ADC data bits
inside a 16-bit container, JPEG / TIFF / BMP files, a colour (Bayer) sensor
(``crossline.sim.colour``), laser-plane poses with the laser always on, any subset of the
parts (camera, lasers, handeye, scans), a noisier arm; a ball bar's three scans besides the
rig's own (ISO 10360-8's sphere-spacing error). ``truth.json`` then records them under
``capture_options``; a random rig (``crossline.sim.random_rig``) its draw under ``rig_draw``.

The code lives in modules beside this one (issue 21.3): ``capture_jobs`` (``Plan``,
``Output``, the render jobs the workers run), ``capture_files`` (rig.yaml and the CSV tables)
and ``capture_truth`` (``truth.json``, whose format it describes, and the true centreline
rows). This one resolves the options (``simulate``), plans the jobs, renders them and writes
the tables (``_render_all``), and re-exports the names its importers use, so
``from crossline.sim.capture import ...`` works as before.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np

from crossline.board import Board
from crossline.errors import CrosslineError
from crossline.geometry import invert_transform, transform_to_pose
from crossline.io.atomic import write_json, write_parquet
from crossline.sim import arm as arm_mod
from crossline.sim import views as views_mod
from crossline.sim.capture_files import _fmt, _pose_row, _probed_datum, _write_csv, _write_rig_yaml
from crossline.sim.capture_jobs import ALWAYS_ON_AMBIENT, Output, Plan, _rng, _run, _worker_init
from crossline.sim.capture_jobs import KIND_SCAN as KIND_SCAN
from crossline.sim.capture_jobs import _board_centre as _board_centre
from crossline.sim.capture_jobs import _light_base as _light_base
from crossline.sim.capture_jobs import _model as _model
from crossline.sim.capture_truth import _frame_table, _truth_json
from crossline.sim.colour import CHANNELS, laser_wavelength
from crossline.sim.part import part_mesh, write_ply, write_stl
from crossline.sim.presets import PRESETS, RigPreset, ball_bar_scans
from crossline.sim.random_rig import RANDOM_PRESETS, random_rig
from crossline.sim.scenes import freeform_part, nominal_frame, scan_scene

__all__ = ["IMAGE_FORMATS", "PARTS", "simulate"]

LASER_STATES = ("A", "B", "AB", "off")
PARTS = ("camera", "lasers", "handeye", "scans")  # what a capture may hold
IMAGE_FORMATS = {"png": ".png", "jpeg": ".jpg", "tiff": ".tif", "bmp": ".bmp"}
EIGHT_BIT_ONLY = ("jpeg", "bmp")
DENT_SIGMA_MM = 2.5  # a dent's default width (Gaussian sigma): a pressed-in defect of ~6 mm
DENT_AT = (0.35, 0.2)  # its plan position on the unit part: on the top, off its middle
NOMINAL_TOL_MM = 1e-3  # chordal tolerance of a freeform's nominal STL, as a CAD export sets it
SCAN_CHUNK = 3  # frames per job: small jobs, so that the two workers finish together


# ----------------------------------------------------------------------------- planning


def _resolve(preset: RigPreset | str, seed: int = 0) -> RigPreset:
    if isinstance(preset, RigPreset):
        return preset
    if preset in RANDOM_PRESETS:
        return random_rig(seed, small=preset == "random-small")
    if preset not in PRESETS:
        raise CrosslineError(f"unknown preset {preset!r}; expected one of "
                             f"{sorted(PRESETS) + list(RANDOM_PRESETS)}")
    return PRESETS[preset]


def _states_of(lasers: tuple[str, ...]) -> tuple[str, ...]:
    return ("A", "off") if lasers == ("A",) else LASER_STATES


def simulate(
    out: Path | str,
    preset: str | RigPreset = "paper",
    seed: int = 0,
    quick: bool = False,
    frames: int | None = None,
    pattern: list[str] | None = None,
    bit_depth: int | None = None,
    scans: list[str] | None = None,
    force: bool = False,
    threads: int = 1,
    progress: bool = True,
    board: Board | None = None,
    data_bits: int | None = None,
    lasers: tuple[str, ...] | list[str] | None = None,
    image_format: str = "png",
    jpeg_quality: int = 95,
    colour: str | None = None,
    laser_always_on: bool = False,
    calibration_only: bool = False,
    arm_noise_scale: float = 1.0,
    parts: tuple[str, ...] | list[str] | None = None,
    dent_mm: float | None = None,
    dent_sigma_mm: float = DENT_SIGMA_MM,
    nominal_datum: bool = False,
    ball_bar: bool = False,
) -> Path:
    """Render a complete capture folder of a virtual rig at ``out``; return its path.

    ``preset``: ``paper``, ``compact``, ``random`` or ``random-small`` (a rig drawn from
    ``seed``, see ``crossline.sim.random_rig``) or a ``RigPreset``. ``board`` replaces the
    preset's calibration board (pattern, size, spacing), printed in the preset's albedos on a
    plate of the preset's margin. The options of real captures:

    * ``bit_depth`` (8 or 16, the container) and ``data_bits`` (8, 10, 12, 14, 16: the ADC's
      range in it, default the rig's; rig.yaml ``sensor.data_bits`` when below the container);
    * ``lasers=("A",)``: a one-line rig (laser A only, every scan frame ``A`` by default);
    * ``image_format`` png | jpeg | tiff | bmp (``jpeg_quality``; jpeg and bmp 8-bit only);
    * ``colour`` red | green | blue: a colour (Bayer) sensor whose laser shows mainly in that
      channel (its wavelength moved into the channel's band if outside), rig.yaml
      ``sensor.channel``; None or ``none``: grey;
    * ``laser_always_on``: laser-plane poses as ``<pose>_laser.*`` only, taken in room light
      (half the board views') with the laser on; camera and hand-eye views unchanged;
    * ``parts``: which of camera, lasers, handeye, scans to write (default all);
      ``calibration_only`` drops scans (no ``scans:`` in rig.yaml);
    * ``arm_noise_scale``: the arm's reported-pose noise times this (position and rotation).

    ``dent_mm``: every freeform part gets a dent this deep (Gaussian profile of
    ``dent_sigma_mm``, on the part's top, off its middle: DENT_AT) that its nominal mesh does not
    have: a defect for the nominal comparison to find (truth.json: the scan's ``dent``).
    ``nominal_datum``: rig.yaml gives each freeform's placement on the table
    (``nominal_pose``), as a user measures it by probing the part's datums with the arm: the
    true placement with a probing error drawn from the arm's precision (truth.json: the
    scan's ``nominal_pose_error``).
    ``ball_bar``: three more scans, ``bar_1`` .. ``bar_3``, of a ball bar (two balls of the
    rig's ball scan's diameter at a calibrated centre distance, for ISO 10360-8's
    sphere-spacing error SD) in three positions (``crossline.sim.presets.ball_bar_scans``).
    """
    rig = _resolve(preset, int(seed))
    if board is not None:
        rig = dataclasses.replace(rig, board=dataclasses.replace(rig.board, board=board))
    out = Path(out)
    if lasers is not None:
        lasers = tuple(lasers)
        if lasers not in (("A",), ("A", "B")):
            raise CrosslineError(f"lasers {list(lasers)}: expected [A] (a one-line rig) or [A, B]")
        rig = dataclasses.replace(rig, lasers={k: rig.lasers[k] for k in lasers})
    rig_lasers = tuple(rig.lasers)
    states = _states_of(rig_lasers)
    if pattern:
        pattern = list(pattern)
    elif rig_lasers == ("A",):
        pattern = ["A"]
    else:
        pattern = list(rig.pattern)
    bad = [s for s in pattern if s not in states]
    if bad or not pattern:
        raise CrosslineError(f"laser pattern {pattern}: states must be among {states}")
    if image_format not in IMAGE_FORMATS:
        raise CrosslineError(f"image format {image_format!r}: expected one of {sorted(IMAGE_FORMATS)}")
    if not 1 <= int(jpeg_quality) <= 100:
        raise CrosslineError(f"JPEG quality must be 1..100, got {jpeg_quality}")
    if image_format in EIGHT_BIT_ONLY and bit_depth is None and data_bits is None:
        bit_depth = data_bits = 8  # a JPEG or BMP camera writes 8-bit data
    if data_bits is not None and bit_depth is None:
        bit_depth = 8 if int(data_bits) == 8 else 16
    bits = int(bit_depth or rig.sensor.bit_depth)
    if bits not in (8, 16):
        raise CrosslineError(f"bit depth must be 8 or 16, got {bits}")
    dbits = int(data_bits or min(rig.sensor.data_bits or bits, bits))
    if dbits not in (8, 10, 12, 14, 16) or dbits > bits:
        raise CrosslineError(f"data bits must be 8, 10, 12, 14 or 16 and at most the bit depth "
                             f"({bits}), got {dbits}")
    if image_format in EIGHT_BIT_ONLY and bits != 8:
        raise CrosslineError(f"{image_format} images hold 8-bit data only; this capture is "
                             f"{bits}-bit (give bit_depth 8)")
    if colour in (None, "none", "grey"):
        colour = None
    elif colour not in CHANNELS:
        raise CrosslineError(f"colour {colour!r}: expected one of {list(CHANNELS)} or none")
    else:
        rig = dataclasses.replace(rig, lasers={
            k: dataclasses.replace(v, wavelength_nm=laser_wavelength(colour, v.wavelength_nm))
            for k, v in rig.lasers.items()})
    if not arm_noise_scale >= 0:
        raise CrosslineError(f"arm noise scale must be >= 0, got {arm_noise_scale}")
    if arm_noise_scale != 1.0:
        a = rig.arm
        rig = dataclasses.replace(rig, arm=dataclasses.replace(
            a, precision_mm=a.precision_mm * arm_noise_scale,
            rot_sigma_rad=a.rot_sigma_rad * arm_noise_scale))
    if dent_mm is not None:
        if not (0.0 < float(dent_mm) <= 2.0 and 0.2 <= float(dent_sigma_mm) <= 20.0):
            raise CrosslineError(f"a dent {dent_mm} mm deep of sigma {dent_sigma_mm} mm: expected a "
                                 "depth in (0, 2] mm and a sigma in [0.2, 20] mm")
        if not any(sp.artefact == "freeform" for sp in rig.scans):
            raise CrosslineError(f"preset {rig.name} has no freeform part to put a dent in")
        dent = {"depth_mm": float(dent_mm), "sigma_mm": float(dent_sigma_mm), "at": DENT_AT}
        rig = dataclasses.replace(rig, scans=tuple(
            dataclasses.replace(sp, params={**sp.params, "dent": dent})
            if sp.artefact == "freeform" else sp for sp in rig.scans))
    if ball_bar:
        try:
            rig = dataclasses.replace(rig, scans=rig.scans + ball_bar_scans(rig))
        except ValueError as exc:
            raise CrosslineError(f"ball bar: {exc}") from None
    parts = tuple(PARTS if parts is None else parts)
    unknown = sorted(set(parts) - set(PARTS))
    if unknown or not parts:
        raise CrosslineError(f"parts {list(parts)}: expected some of {list(PARTS)}")
    if calibration_only:
        parts = tuple(p for p in parts if p != "scans")
    parts = tuple(p for p in PARTS if p in parts)
    names = [s.name for s in rig.scans]
    wanted = list(scans) if scans else names
    unknown = [s for s in wanted if s not in names]
    if unknown:
        raise CrosslineError(f"unknown scan(s) {unknown} for preset {rig.name}; known: {names}")
    if "scans" not in parts:
        wanted = []
    if frames is not None and frames < 1:
        raise CrosslineError(f"frames must be >= 1, got {frames}")
    output = Output(data_bits=None if dbits == bits else dbits, ext=IMAGE_FORMATS[image_format],
                    jpeg_quality=int(jpeg_quality), colour=colour, always_on=bool(laser_always_on),
                    nominal_datum=bool(nominal_datum))
    options = {"parts": list(parts), "image_format": image_format, "colour": colour,
               "laser_always_on": bool(laser_always_on), "arm_noise_scale": float(arm_noise_scale),
               "lasers": list(rig_lasers), "data_bits": dbits}
    if image_format == "jpeg":
        options["jpeg_quality"] = int(jpeg_quality)
    if nominal_datum:
        options["nominal_datum"] = True
    if ball_bar:
        options["ball_bar"] = True
    if dent_mm is not None:
        options["dent_mm"] = float(dent_mm)
        options["dent_sigma_mm"] = float(dent_sigma_mm)
    notes = ([f"laser {rig_lasers[0]} only"] if len(rig_lasers) == 1 else []) + (
        [f"colour sensor, {colour} laser"] if colour else []) + (
        ["laser always on"] if laser_always_on else []) + (
        [f"arm noise x{arm_noise_scale:g}"] if arm_noise_scale != 1.0 else []) + (
        [f"a {dent_mm:g} mm dent in the freeform part"] if dent_mm is not None else []) + (
        ["a ball bar in three positions"] if ball_bar else [])
    if notes:
        rig = dataclasses.replace(rig, description=f"{rig.description}; {', '.join(notes)}")
    if out.exists():
        if not out.is_dir():
            raise CrosslineError(f"{out}: exists and is not a folder")
        if any(out.iterdir()) and not force:
            raise CrosslineError(f"{out}: folder is not empty; use --force to overwrite it")

    partial = out.parent / f"{out.name}.partial-{os.getpid()}"
    if partial.exists():
        shutil.rmtree(partial)
    partial.mkdir(parents=True)
    try:
        _render_all(rig, partial, int(seed), quick, frames, pattern, bits, wanted, threads, progress,
                    output, parts, options)
        if out.exists():
            shutil.rmtree(out)
        os.rename(partial, out)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return out



def _render_all(rig: RigPreset, root: Path, seed: int, quick: bool, frames: int | None,
                pattern: list[str], bits: int, scan_names: list[str], threads: int,
                progress: bool, output: Output = Output(), parts: tuple[str, ...] = PARTS,  # noqa: B008
                options: dict | None = None) -> None:
    import pandas as pd

    from crossline.camera import Camera

    cal = rig.quick_calibration if quick else rig.calibration
    s = rig.sensor
    cam = Camera(np.array(s.K), np.array(s.dist), (s.width, s.height))
    plan = Plan(rig, seed, bits, root, out=output)
    ext = output.ext
    truth_cal: dict[str, Any] = {"camera": {}, **{f"laser_{k}": {} for k in rig.lasers},
                                 "handeye": {}}

    # camera views
    if "camera" in parts:
        for i, T in enumerate(views_mod.camera_views(cam, rig.board, cal, cal.camera_views)):
            rel = f"calibration/camera/view_{i:02d}{ext}"
            plan.jobs.append(("camera", i, T, rel))
            truth_cal["camera"][f"view_{i:02d}{ext}"] = {"T_cam_board": T}
    # laser views
    for li, laser in enumerate(("A", "B")):
        if "lasers" not in parts or laser not in rig.lasers:
            continue
        vs = views_mod.laser_views(cam, rig.board, rig.lasers[laser], cal.laser_depths_mm,
                                   cal.laser_poses, phase=0.7 * li)
        for i, T in enumerate(vs):
            pose = f"pose_{i:02d}"
            board_rel = None if output.always_on else f"calibration/laser_{laser}/{pose}_board{ext}"
            plan.jobs.append(("laser", laser, i, T, board_rel,
                              f"calibration/laser_{laser}/{pose}_laser{ext}"))
            truth_cal[f"laser_{laser}"][pose] = {"T_cam_board": T}
    # hand-eye views
    X = rig.T_tool_cam
    he_rows = []
    if "handeye" in parts:
        he = views_mod.handeye_views(cam, rig, cal.handeye_views, cal.handeye_distance_mm)
        T_tool_true = np.array([arm_mod.tool_from_cam(T, X) for T in he])
        T_tool_rep, dp, dth = arm_mod.noise_calibration(T_tool_true, rig.arm, _rng(seed, 90))
        for i, T in enumerate(he):
            name = f"pose_{i:02d}{ext}"
            plan.jobs.append(("handeye", i, invert_transform(T), f"calibration/handeye/{name}"))
            he_rows.append([name, *_pose_row(T_tool_rep[i])])
            truth_cal["handeye"][name] = {
                "T_base_tool": T_tool_true[i], "T_cam_board": invert_transform(T) @ rig.T_base_board,
                "error_position_mm": dp[i], "error_rotation_rad": dth[i],
            }

    # scans
    scan_truth: dict[str, Any] = {}
    datums: dict[str, list[float]] = {}
    scan_tables: dict[str, list] = {}
    scan_stats: dict[str, list] = {}
    frame_rows: dict[str, list] = {}
    pose_frames: dict[str, pd.DataFrame] = {}
    for si, spec in enumerate(rig.scans):
        if spec.name not in scan_names:
            continue
        n = frames or (rig.quick_frames if quick else spec.frames)
        if quick and frames is None and spec.quick_frames is not None:
            n = spec.quick_frames
            spec = dataclasses.replace(spec, frames=n)  # its whole sweep, faster
        scene, truth, aim = scan_scene(rig, spec)
        times, T_base_cam = arm_mod.scan_trajectory(rig, spec, aim, n)
        T_tool_true = arm_mod.tool_from_cam(T_base_cam, X)
        T_tool_rep, dp, dth = arm_mod.noise_scan(T_tool_true, rig.arm, 1.0 / s.frame_rate,
                                                 _rng(seed, 91, si))
        states = [pattern[k % len(pattern)] for k in range(n)]
        T_cam_base = invert_transform(T_base_cam)
        fr = [(k, states[k], T_cam_base[k]) for k in range(n)]
        for a in range(0, n, SCAN_CHUNK):
            plan.jobs.append(("scan", si, spec.name, fr[a : a + SCAN_CHUNK]))
        frame_rows[spec.name] = [
            [str(k), _fmt(times[k]), states[k], *_pose_row(T_tool_rep[k])] for k in range(n)
        ]
        p, q = transform_to_pose(T_tool_true)
        pose_frames[spec.name] = pd.DataFrame({
            "frame": np.arange(n), "time_s": times, "lasers": states,
            "x": p[:, 0], "y": p[:, 1], "z": p[:, 2],
            "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3],
            "err_x": dp[:, 0], "err_y": dp[:, 1], "err_z": dp[:, 2],
            "err_rx": dth[:, 0], "err_ry": dth[:, 1], "err_rz": dth[:, 2],
        })
        speed = spec.sweep_mm / ((spec.frames - 1) / s.frame_rate)
        scan_truth[spec.name] = {
            **truth,
            "centrelines": f"truth/{spec.name}_centrelines.parquet",
            "poses": f"truth/{spec.name}_poses.parquet",
            "surfaces": [pr.name for pr in scene.prims],
            "frames": n,
            "pattern": pattern,
            "trajectory": {"speed_mm_s": speed, "distance_mm": spec.distance_mm,
                           "tilt_deg": spec.tilt_deg, "heading_deg": spec.heading_deg,
                           "aim_base": aim},
        }
        if spec.sweep_incline_deg:
            scan_truth[spec.name]["trajectory"]["incline_deg"] = spec.sweep_incline_deg
        if spec.artefact == "freeform":
            scan_truth[spec.name]["mesh"] = "truth/part.ply"
        scan_tables[spec.name] = []
        scan_stats[spec.name] = []

    # render
    n_images = sum(1 if j[0] in ("camera", "handeye") else len(j[3]) if j[0] == "scan"
                   else 1 if j[4] is None else 2 for j in plan.jobs)
    order = sorted(range(len(plan.jobs)), key=lambda k: (plan.jobs[k][0] == "scan", k))
    jobs = [plan.jobs[k] for k in order]
    from tqdm import tqdm

    with tqdm(total=n_images, disable=not progress, file=sys.stderr, unit="img",
              desc=f"simulate {rig.name}") as bar:
        def take(res):
            kind, payload, count = res
            if kind == "scan":
                name, tables, stats = payload
                scan_tables[name].extend(_frame_table(*t) for t in tables)
                scan_stats[name].extend(stats)
            bar.update(count)

        if threads <= 1:
            from threadpoolctl import threadpool_limits

            with threadpool_limits(limits=1):  # as in the workers (see _worker_init)
                for j in jobs:
                    take(_run(plan, j))
        else:
            import multiprocessing as mp

            light = Plan(plan.preset, plan.seed, plan.bits, plan.root, out=plan.out)  # no job list
            # forkserver, not fork: forking a process that already runs threads (BLAS, numba,
            # a test runner's) can deadlock the child; the server is a fresh interpreter
            ctx = mp.get_context("forkserver")
            ctx.set_forkserver_preload(["crossline.sim.capture"])
            with ProcessPoolExecutor(max_workers=threads, mp_context=ctx,
                                     initializer=_worker_init) as ex:
                futs = [ex.submit(_run, light, j) for j in jobs]
                for f in as_completed(futs):
                    take(f.result())

    # tables
    if "handeye" in parts:
        (root / "calibration" / "handeye").mkdir(parents=True, exist_ok=True)
        _write_csv(root / "calibration" / "handeye" / "poses.csv",
                   ["image", "x", "y", "z", "qw", "qx", "qy", "qz"], he_rows)
    truth_dir = root / "truth"
    for name in frame_rows:
        _write_csv(root / "scans" / name / "frames.csv",
                   ["frame", "time_s", "lasers", "x", "y", "z", "qw", "qx", "qy", "qz"],
                   frame_rows[name])
        tab = (pd.concat(scan_tables[name], ignore_index=True) if scan_tables[name]
               else pd.DataFrame(columns=["frame", "laser", "u", "v", "x_cam", "y_cam", "z_cam",
                                          "visible", "lit", "unoccluded", "surface", "cos_view",
                                          "cos_incidence", "peak_e", "sigma_px", "background_e"]))
        tab = tab.sort_values(["frame", "laser", "u", "v"], kind="mergesort").reset_index(drop=True)
        tab = tab.astype({"frame": "int64", "u": "int64", "v": "float64", "x_cam": "float64",
                          "y_cam": "float64", "z_cam": "float64", "visible": "bool", "lit": "bool",
                          "unoccluded": "bool", "surface": "str", "laser": "str",
                          "cos_view": "float64", "cos_incidence": "float64", "peak_e": "float64",
                          "sigma_px": "float64", "background_e": "float64"})
        write_parquet(truth_dir / f"{name}_centrelines.parquet", tab)
        write_parquet(truth_dir / f"{name}_poses.parquet", pose_frames[name])
        st = sorted(scan_stats[name], key=lambda r: r["frame"])
        if st:
            peaks = np.array([r["peak_dn"] for r in st])
            scan_truth[name]["render_stats"] = {
                "peak_dn_median": float(np.median(peaks)), "peak_dn_max": int(peaks.max()),
                "band_px_median": float(np.median([r.get("band_px", 0) for r in st])),
                "fine_px_median": float(np.median([r.get("fine_px", 0) for r in st])),
            }
        spec = next(sp for sp in rig.scans if sp.name == name)
        if spec.artefact == "freeform":
            V, F = part_mesh(freeform_part(rig, spec))
            write_ply(truth_dir / "part.ply", V, F)
            scan_truth[name]["mesh_triangles"] = len(F)
            # its drawing: the design surface in the part's own frame, exported as a CAD
            # system would (an STL within NOMINAL_TOL_MM of the surface)
            T = nominal_frame(rig, spec)
            # (the drawing has no dent: a dent is the defect the comparison is to find)
            Vn, Fn = part_mesh(dataclasses.replace(freeform_part(rig, spec), dent=None), NOMINAL_TOL_MM)
            write_stl(root / f"{name}.stl", (Vn - T[:3, 3]) @ T[:3, :3], Fn,
                      f"crossline virtual rig: nominal of scan {name}, mm")
            scan_truth[name]["T_base_nominal"] = T.tolist()
            if output.nominal_datum:
                datums[name], scan_truth[name]["nominal_pose_error"] = _probed_datum(
                    T, rig, _rng(seed, 92, rig.scans.index(spec)))

    truth = _truth_json(rig, seed, quick, bits, pattern, truth_cal, scan_truth, output)
    defaults = {"parts": list(PARTS), "image_format": "png", "colour": None,
                "laser_always_on": False, "arm_noise_scale": 1.0, "lasers": ["A", "B"],
                "data_bits": bits}
    if options is not None and (options != defaults or rig.draw is not None):
        truth["capture_options"] = options
        if output.always_on:
            truth["capture_options"]["always_on_ambient_e_white"] = (
                ALWAYS_ON_AMBIENT * rig.ambient_board_e)
    if rig.draw is not None:
        truth["rig_draw"] = rig.draw
    write_json(root / "truth.json", truth)
    _write_rig_yaml(root / "rig.yaml", rig, bits, scan_names, output, "scans" in parts, datums)
