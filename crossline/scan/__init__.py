"""Scan stages: from scan frames to labelled 3-D points in the arm's base frame.

Module map: ``frames`` (each frame read once, decoded in parallel threads), ``stripes`` (stripe
centres per column: grey centre, Gaussian, Steger; the ``extract-stripes`` stage),
``centreline`` (centres linked into lines and smoothed along the stripe), ``labels`` (which
laser made each centre: the paper's periodic A / B / AB control), ``triangulate`` (pixels to
the camera frame to the base frame; the ``triangulate`` stage), ``refine`` (each frame's arm
pose refined from the scan itself, used by fusion) with its parts ``refine_prior`` (the arm's
error model as prior), ``refine_crossings`` (where A and B stripes cross, and their gaps) and
``refine_solve`` (the MAP solve of every frame's pose error).
"""
