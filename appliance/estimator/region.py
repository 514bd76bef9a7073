"""The answer's credible region, and the notes on an answer the skyline does not single out.

With the noise learned from the best fit, the region is the answer's error ellipse (``confidence.py``)
and the cells of the rival places: other modes of the posterior, and exact fits elsewhere that
rival the best.  With sigma as given, it is the nodes whose upper posterior reaches the best's
lower one.  Either way the answer is ambiguous when the skyline fits poorly, leaves most of
itself to occluders, or leans on the compass's tolerance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from appliance.estimator import confidence
from appliance.estimator.posteriors import SAME_ANSWER_CELLS

#: A region (sigma as given, not learned) wider than this many map cells is reported as ambiguous.
AMBIGUOUS_CELLS = 25
#: A heading correction within this much (deg) of the compass's tolerance is at its limit.
HEADING_LIMIT_MARGIN_DEG = 0.5
#: A best fit that leaves more than this share of the azimuths to occluders has not explained the skyline.
MAX_OCCLUDED_SHARE = 0.5


@dataclass(frozen=True)
class Region:
    """The answer's credible region (node indices) and its area, the rival places' nodes, whether the
    answer is ambiguous or its heading correction at the compass's limit, and the notes saying why."""

    nodes: np.ndarray
    area_m2: float
    rival_nodes: np.ndarray
    ambiguous: bool
    heading_at_limit: bool
    notes: list[str]


def learned_region(conf: confidence.Modes, fit_cells: list[int], answer_node: int, cov_m2: np.ndarray,
                   cell_area_m2: float, heading_deg: float, rms_deg: float, sigma_hi_deg: float, hidden: float,
                   rival_fit: bool, heading_tolerance_deg: float | None) -> Region:
    """The 95 % region at the noise learned: the answer's ellipse (``cov_m2``, m^2) and the cells of
    the rival places (``conf``'s rival modes, the rival fits' nodes ``fit_cells``).  ``hidden`` is
    the share of the skyline the best fit leaves to occluders; ``sigma_hi_deg`` the upper end of the
    sigma interval searched."""
    poor = rms_deg > sigma_hi_deg or hidden > MAX_OCCLUDED_SHARE
    rival_cells = np.union1d(conf.rivals, fit_cells).astype(np.int64)
    region = np.union1d(np.union1d(conf.region, rival_cells), [answer_node]).astype(np.int64)
    area = confidence.ellipse_area_m2(cov_m2) + rival_cells.size * cell_area_m2
    # a heading correction at the compass's limit: the best place may lie with a heading beyond it
    pinned = (heading_tolerance_deg is not None
              and abs(heading_deg) > heading_tolerance_deg - HEADING_LIMIT_MARGIN_DEG)
    ambiguous = bool(rival_cells.size) or poor or pinned
    notes = _quality_notes(conf, rival_cells.size * cell_area_m2, rival_fit, rms_deg, sigma_hi_deg)
    if hidden > MAX_OCCLUDED_SHARE:
        notes.append(f"ambiguous: poor match: {hidden:.0%} of the skyline stands above the map's terrain at the "
                     "best place; the skyline may not come from this map")
    if pinned:
        notes.append(f"ambiguous: the heading correction {heading_deg:+.1f} deg reaches the compass's "
                     f"tolerance of {heading_tolerance_deg:g} deg; the best place may need a larger one")
    if not np.all(np.isfinite(cov_m2)):
        ambiguous = True
        notes.append("ambiguous: the answer's covariance cannot be formed (the fit's curvature is singular)")
    return Region(region, area, rival_cells, ambiguous, pinned, notes)


def given_region(post_region: np.ndarray, fit_cells: list[int], answer_node: int, cell_area_m2: float,
                 rms_deg: float, sigma_hi_deg: float, hidden: float, rival_fit: bool) -> Region:
    """The region with sigma as given: the nodes whose upper posterior reaches the best's lower one
    (``post_region``), the answer's node and the rival fits' (arguments as :func:`learned_region`'s)."""
    poor = rms_deg > sigma_hi_deg or hidden > MAX_OCCLUDED_SHARE
    region = np.union1d(post_region, [answer_node] + fit_cells).astype(np.int64)
    area = region.size * cell_area_m2
    ambiguous = region.size > AMBIGUOUS_CELLS or rival_fit or poor
    notes = _region_notes(region.size, area) + _quality_notes(None, 0.0, rival_fit, rms_deg, sigma_hi_deg)
    return Region(region, area, np.zeros(0, dtype=np.int64), ambiguous, False, notes)


def _quality_notes(conf: confidence.Modes | None, rival_area_m2: float, rival_fit: bool, rms_deg: float,
                   sigma_hi_deg: float) -> list[str]:
    """Notes on an answer the skyline does not single out (rival places of ``conf``, the modes of a
    learned posterior; rival fits) or fits poorly."""
    notes: list[str] = []
    if conf is not None and conf.rivals.size:
        notes.append(
            f"ambiguous: {conf.rival_mass:.0%} of the posterior lies at other places "
            f"({conf.rivals.size} cells, {rival_area_m2 / 1e6:.2f} km^2) inside the {confidence.LEVEL:.0%} region; "
            "the skyline does not single out one position"
        )
    if rival_fit:
        notes.append(
            f"ambiguous: exact renders at another place, more than {SAME_ANSWER_CELLS:.0f} cells away, "
            "fit as well as the best"
        )
    if rms_deg > sigma_hi_deg:
        notes.append(
            f"ambiguous: poor match: residual {rms_deg:.2f} deg RMS, more than the {sigma_hi_deg:.2f} deg the "
            "search allows; the skyline may not come from this map"
        )
    return notes


def _region_notes(region_cells: int, area_m2: float) -> list[str]:
    """The note on a region (sigma as given) too wide to single out one position."""
    if region_cells <= AMBIGUOUS_CELLS:
        return []
    return [f"ambiguous: {region_cells} cells ({area_m2 / 1e6:.2f} km^2) are as likely as the best; "
            "the skyline does not single out one position"]
