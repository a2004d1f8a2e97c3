"""The virtual rig: ``simulate(out, preset, ...)`` writes a complete capture folder with truth.

The folder follows ``shared/DESIGN.md`` §2 exactly (rig.yaml, calibration/, scans/) and adds
``truth.json`` and ``truth/`` (true centrelines, true poses, the freeform's mesh). Everything is
rendered into ``<out>.partial-<pid>`` and renamed to ``<out>`` at the end (rig.yaml written
last), so an interrupted run never leaves a folder that looks complete.

Module map: ``presets`` (the rigs and every number; ``ball_bar_scans``, a ball bar's three
positions derived from a rig's ball scan: ``simulate(..., ball_bar=True)``), ``optics`` (rays
through the distortion, sensor chain, speckle), ``scene`` (analytic primitives: ``vec3``
row-wise vectors, ``primitive`` the base classes, ``planar`` half-spaces and boxes, ``quadrics``
spheres and cylinders, ``freeform`` the part and its dent), ``scenes`` (artefacts: gauge block,
plate, ball, freeform part, ball bar; and the board), ``texture`` (board patterns), ``sheet``
(laser irradiance), ``render`` (an image from its parts: ``rig_model``, the rig's camera,
lasers, sensor and light; ``ambient``, board views and faint ambient light; ``stripe``, the band
and the true stripe; ``band``, laser light in the band), ``arm`` (trajectories and pose noise),
``views`` (calibration poses), ``part`` (the freeform's truth mesh), ``capture`` (this package's
writer, in ``simulate``; ``capture_jobs`` the render jobs, ``capture_files`` rig.yaml and CSVs,
``capture_truth`` truth.json), ``truth`` (the true calibration written as the stages' artefacts,
to score later stages alone), ``random_rig`` (whole rigs drawn from a seed: ``simulate(out,
"random", seed)``), ``colour`` (a Bayer colour sensor).
"""

from __future__ import annotations

from crossline.sim.capture import simulate
from crossline.sim.random_rig import random_rig
from crossline.sim.truth import write_true_calibration

__all__ = ["random_rig", "simulate", "write_true_calibration"]
