"""The fuse stage (workflow/rules/fuse.smk): a scan's points fused into one cloud, PLY.

The package mirrors the rule: ``cloud`` (the cloud, its normals, the voxel grid,
``fuse_cloud`` and ``run_fuse``), ``normals`` (one slab's normals, their orientation),
``refine`` (the pose refinement step and its stats), ``mesh`` (the optional mesh), ``inputs``
(the points parquet's columns, the scan's frames table) and ``camera_centres`` (each frame's
camera centre from its points). Issue 21.3 moved them here from flat modules
(``crossline/fuse.py``, ``fuse_*.py``, ``camera_centres.py``); this module re-exports the names
their importers use, so ``from crossline.fuse import ...`` is unchanged.
"""

from __future__ import annotations

from crossline.fuse import cloud
from crossline.fuse.camera_centres import FrameMoments as FrameMoments
from crossline.fuse.cloud import *  # noqa: F403 (the stage's names, as crossline.fuse had them)

__all__ = cloud.__all__
