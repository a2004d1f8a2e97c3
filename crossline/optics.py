"""The rig's imaging optics as the speckle sees them: the grain of the image's speckle.

One rule, used by the renderer (``crossline.sim.random_rig`` draws a rig's grain from its
lens) and by the speckle bound (``crossline.report.speckle``), so that the two agree.
"""

from __future__ import annotations

__all__ = ["GRAIN_LAMBDA_N", "grain_px"]

GRAIN_LAMBDA_N = 0.41  # the image grain's sigma (the field's Gaussian) per lambda x N (1 + m)


def grain_px(wavelength_nm: float, f_number: float, pixel_um: float,
             magnification: float = 0.0) -> float:
    """The image's speckle grain (px): sigma of the Gaussian that correlates the field, as the
    renderer draws it (``crossline.sim.optics.speckle_field``) from the optics."""
    return GRAIN_LAMBDA_N * wavelength_nm * 1e-3 * f_number * (1.0 + magnification) / pixel_um
