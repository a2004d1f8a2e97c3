"""The summary rows of a report: each figure against its tolerance, with its uncertainty.

``_check`` appends one row (a figure, its tolerance, PASS / FAIL / INFO / N/A);
``_with_uncertainty`` gives a row its expanded uncertainty U and the ISO 14253-1 decision,
from the Monte Carlo figure ``ROW_FIGURES`` names for it. Split from
``crossline.report.accuracy`` (issue 21.3), which re-exports the names its importers use.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["ROW_FIGURES"]


def _check(
    rows: list, cid: str, label: str, scan: str | None, value: float | None, unit: str,
    limit: float | None, comparison: str = "<=", use_abs: bool = False, note: str = "",
) -> None:
    """Append one summary row: a figure, its tolerance and whether it passes."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        status = "N/A"
    elif limit is None:
        status = "INFO"
    else:
        v = abs(value) if use_abs else value
        status = "PASS" if (v <= limit if comparison == "<=" else v >= limit) else "FAIL"
    rows.append({"id": cid, "figure": label, "scan": scan, "value": value, "unit": unit,
                 "abs": use_abs, "comparison": comparison, "tolerance": limit,
                 "status": status, "note": note})


# the Monte Carlo figure whose uncertainty a summary row's value has
# (sphere_form_error_mm: the configured form statistic's)
ROW_FIGURES = {"gauge_mean_error_mm": "mean_mm", "plane_within_share": "share_within_band",
               "plane_flatness_95_mm": "flatness_95_mm", "sphere_size_error_mm": "diameter_mm",
               "sphere_form_error_d95_mm": "form_error_d95_mm",
               "sphere_form_error_vdi_mm": "form_error_vdi_mm", "plane_flatness_mm": "flatness_mm",
               "ball_bar_sd_mm": "length_mm", "nominal_within_share": "share_within_tolerance"}


def _with_uncertainty(row: dict, unc: dict | None, form_key: str) -> None:
    """Give a summary row its expanded uncertainty U (k = 2) and the ISO 14253-1 decision.

    Conformance is proven where the value is inside the limit by at least U, non-conformance
    where it is outside by more than U; in between the result is inconclusive (the PASS/FAIL
    status stays the plain comparison of the value).
    """
    key = form_key if row["id"] == "sphere_form_error_mm" else ROW_FIGURES.get(row["id"])
    fig = ((unc or {}).get("figures") or {}).get(key) if key else None
    if fig is None or row["value"] is None or not np.isfinite(fig["U"]):
        return  # no U where the draws leave it undetermined (too few frames): no decision either
    U = float(fig["U"])
    row["U"] = U
    row["k"] = fig["k"]
    row["dominant"] = fig["dominant"]
    if row["tolerance"] is None:
        return
    v = abs(row["value"]) if row["abs"] else row["value"]
    lim = row["tolerance"]
    inside, outside = (v + U <= lim, v - U > lim) if row["comparison"] == "<=" else \
        (v - U >= lim, v + U < lim)
    row["decision"] = ("conforms" if inside else "does not conform" if outside
                       else "inconclusive (within U of the limit)")
