"""The capture's render jobs: what the workers receive (``Plan``, ``Output``) and how they run one.

``_run`` renders one job (a camera view, a laser-plane pose, a hand-eye view or a chunk of
scan frames) with its own random generator (``_rng``, seeded from ``(seed, kind, index)``)
and writes its images (``_write``); ``_model`` and the scenes are cached per worker process,
``_worker_init`` sets a worker up (one BLAS and OpenCV thread), ``_light_board`` and
``_light_base`` give the ambient light of board views and of table scenes. Split from
``crossline.sim.capture`` (issue 21.3), which re-exports the names its importers use.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from crossline.io.images import write_image, write_png
from crossline.sim.colour import ColourSensor
from crossline.sim.presets import RigPreset
from crossline.sim.render import Light, RigModel, render_image
from crossline.sim.scenes import board_scene_free, board_scene_table, scan_scene

__all__ = ["ALWAYS_ON_AMBIENT", "GRAD_MM", "KIND_CAMERA", "KIND_HANDEYE", "KIND_LASER", "KIND_SCAN",
           "Output", "Plan"]

ALWAYS_ON_AMBIENT = 0.5  # laser-on poses without a twin: room light at this share of the board views'
KIND_CAMERA, KIND_LASER, KIND_HANDEYE, KIND_SCAN = 1, 2, 3, 4
GRAD_MM = 0.0015  # relative change of ambient light per mm across the scene


@dataclass(frozen=True)
class Output:
    """How images are written: ADC bits, file format, colour, laser-on poses without a twin."""

    data_bits: int | None = None  # None: the container's
    ext: str = ".png"
    jpeg_quality: int = 95
    colour: str | None = None  # the laser's channel of a colour (Bayer) sensor
    always_on: bool = False
    nominal_datum: bool = False  # rig.yaml gives each freeform's placement (nominal_pose)


@dataclass
class Plan:
    """Everything the workers need, decided up front (picklable)."""

    preset: RigPreset
    seed: int
    bits: int
    root: Path
    jobs: list = field(default_factory=list)
    out: Output = Output()


# ----------------------------------------------------------------------------- workers

_MODELS: dict = {}
_SCENES: dict = {}


def _model(plan: Plan) -> RigModel:
    # a worker receives a fresh copy of the preset with every job: key on its content
    key = (plan.preset.name, plan.bits, plan.seed, repr(plan.preset), plan.out)
    if key not in _MODELS:
        _MODELS.clear()
        _SCENES.clear()
        _MODELS[key] = RigModel(plan.preset, plan.bits, plan.seed, plan.out.data_bits)
        c = plan.out.colour
        _MODELS[key].colour = None if c is None else ColourSensor(
            c, {k: v.wavelength_nm for k, v in plan.preset.lasers.items()})
    return _MODELS[key]


def _write(plan: Plan, rel: str, img: np.ndarray) -> None:
    """One image of the capture in its format (grey PNG: the fixed-encoding writer)."""
    path = plan.root / rel
    if img.ndim == 2 and path.suffix == ".png":
        write_png(path, img)
    else:
        write_image(path, img, jpeg_quality=plan.out.jpeg_quality)


def _worker_init() -> None:
    """Set up a render worker: one BLAS and OpenCV thread, a malloc that keeps its memory.

    One BLAS thread: the workers are the parallelism; a second BLAS thread would only spin
    (OpenBLAS busy-waits after every product: seconds of CPU for the ray tables' products),
    and the rendering in one process (``threads=1``) uses one BLAS thread too, so that the
    bytes cannot depend on the number of processes.

    Every image allocates and frees arrays of tens of MB. glibc hands blocks that large to
    mmap and back to the kernel on free, so the next image faults the same memory in again,
    page by page (seconds of system time for the --quick capture; bench_render prints it).
    In a worker, which exits when the render ends, freed memory is kept for reuse instead:
    same arithmetic, same bytes, fewer page faults.
    """
    from threadpoolctl import threadpool_limits

    cv2.setNumThreads(1)
    threadpool_limits(limits=1)  # for the life of the worker
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL("libc.so.6")
            libc.mallopt(-3, 1 << 30)  # M_MMAP_THRESHOLD: blocks below 1 GB come from the heap
            libc.mallopt(-1, 1 << 30)  # M_TRIM_THRESHOLD: keep up to 1 GB of free heap
        except (OSError, AttributeError):  # pragma: no cover - not glibc
            pass


def _light_board(T_cam_board: np.ndarray, e_white: float, centre_board: np.ndarray) -> Light:
    R = T_cam_board[:3, :3]
    return Light(e_white, R @ np.array([0.0, 0.0, -1.0]), R @ np.array([GRAD_MM, -0.6 * GRAD_MM, 0.0]),
                 R @ centre_board + T_cam_board[:3, 3])


def _light_base(T_cam_base: np.ndarray, e_white: float, ref_base: np.ndarray) -> Light:
    R = T_cam_base[:3, :3]
    return Light(e_white, R @ np.array([0.0, 0.0, 1.0]), R @ np.array([0.8 * GRAD_MM, GRAD_MM, 0.0]),
                 R @ ref_base + T_cam_base[:3, 3])



def _rng(seed: int, *key: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), *[int(k) for k in key]])


def _board_centre(preset: RigPreset) -> np.ndarray:
    ex, ey = preset.board.board.extent()
    return np.array([ex / 2, ey / 2, 0.0])


def _run(plan: Plan, job: tuple) -> tuple[str, Any, int]:
    """Render one job; returns (kind, result, number of images written)."""
    cv2.setNumThreads(1)
    model = _model(plan)
    preset = plan.preset
    kind = job[0]
    full = model.sensor_window
    colour = model.colour
    if kind == "camera":
        _, i, T, rel = job
        scene = board_scene_free(preset.board).transformed(T)
        light = _light_board(T, preset.ambient_board_e, _board_centre(preset))
        dn, _, _ = render_image(model, scene, light, full, (), _rng(plan.seed, KIND_CAMERA, i),
                                ambient="full", truth=False, colour=colour)
        _write(plan, rel, dn)
        return kind, None, 1
    if kind == "laser":
        _, laser, i, T, rel_board, rel_laser = job
        li = "AB".index(laser)
        scene = board_scene_free(preset.board).transformed(T)
        if rel_board is not None:
            light = _light_board(T, preset.ambient_board_e, _board_centre(preset))
            dn, _, _ = render_image(model, scene, light, full, (),
                                    _rng(plan.seed, KIND_LASER, li, i, 0), ambient="full",
                                    truth=False, colour=colour)
            _write(plan, rel_board, dn)
            # the room light of the laser-on image traced like the board view's ("full"), not
            # interpolated from a coarse grid as in scan frames: calibration subtracts the two
            # images, and a smeared board there would leave the board's edges in the difference
            light = _light_board(T, preset.ambient_scan_e, _board_centre(preset))
            dn, _, _ = render_image(model, scene, light, full, (laser,),
                                    _rng(plan.seed, KIND_LASER, li, i, 1), ambient="full",
                                    truth=False, colour=colour)
        else:  # laser always on: one image in which the board must be found despite the stripe
            light = _light_board(T, ALWAYS_ON_AMBIENT * preset.ambient_board_e, _board_centre(preset))
            dn, _, _ = render_image(model, scene, light, full, (laser,),
                                    _rng(plan.seed, KIND_LASER, li, i, 1), ambient="full",
                                    truth=False, colour=colour)
        _write(plan, rel_laser, dn)
        return kind, None, 1 if rel_board is None else 2
    if kind == "handeye":
        _, i, T_cam_base, rel = job
        key = ("handeye",)
        if key not in _SCENES:
            _SCENES[key] = board_scene_table(preset)
        scene = _SCENES[key].transformed(T_cam_base)
        centre = preset.T_base_board[:3, :3] @ _board_centre(preset) + preset.T_base_board[:3, 3]
        light = _light_base(T_cam_base, preset.ambient_board_e, centre)
        dn, _, _ = render_image(model, scene, light, full, (), _rng(plan.seed, KIND_HANDEYE, i),
                                ambient="full", truth=False, colour=colour)
        _write(plan, rel, dn)
        return kind, None, 1
    if kind == "scan":
        _, si, name, frames = job
        spec = next(s for s in preset.scans if s.name == name)
        key = ("scan", name)
        if key not in _SCENES:
            _SCENES[key] = scan_scene(preset, spec)
        scene_base, _, aim = _SCENES[key]
        tables = []
        stats = []
        for frame, state, T_cam_base in frames:
            lasers = () if state == "off" else tuple(state)
            scene = scene_base.transformed(T_cam_base)
            light = _light_base(T_cam_base, preset.ambient_scan_e, aim)
            dn, rows, st = render_image(model, scene, light, model.scan_window, lasers,
                                        _rng(plan.seed, KIND_SCAN, si, frame), ambient="coarse",
                                        colour=colour)
            _write(plan, f"scans/{name}/frames/{frame:06d}{plan.out.ext}", dn)
            # plain arrays: the parent makes the tables (workers never import pandas)
            tables.extend((frame, laser, r) for laser, r in rows.items() if r is not None)
            stats.append({"frame": frame, "peak_dn": int(dn.max()), **st})
        return kind, (name, tables, stats), len(frames)
    raise ValueError(f"unknown job {kind!r}")
