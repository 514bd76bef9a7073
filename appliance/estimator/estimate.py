"""Position (and heading) from one measured skyline against a skyline database.

Candidates are theta = (node, heading correction phi).  One search (:func:`estimate` may make a
second, below) goes:

1. The measured skyline resampled onto the database's azimuth grid (``measurement.py``).
2. Every node scored cheaply on skylines averaged over runs of azimuths (``coarse.py``): with a
   compass, phi spans +-beta around zero; with none, every phi, keeping each node's best band of
   headings.  The plausible nodes, and only they, are scored again on every azimuth
   (``rescore.py``).  Nodes left on the first pass are far less likely than the best (hundreds of
   nats), so their first-pass score stands in for the full one in the posterior's sums.
3. Lower and upper likelihoods over sigma in [sigma_l, sigma_u], then the lower and upper
   posteriors (``likelihood.py``, ``posteriors.py``) under the prior (uniform, or the fused one).
4. Best estimate: the candidate with the highest lower posterior.  Region: the nodes holding a
   candidate whose upper posterior reaches the best's lower posterior.
5. The answer refined between nodes (``refinement.py``): exact renders of the terrain fitted in
   position, heading and eye height (``exact.py``), or, without terrain, a blend of the database's
   skylines (``subcell.py``).

With an exact fit the noise is then learned from its residuals (``noise.py``), the posteriors made
again at that noise, and the answer's credible region drawn (``region.py``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from appliance.estimator import confidence
from appliance.estimator.coarse import FirstPass, first_pass_bounds, scored_first_pass
from appliance.estimator.exact import Fit, PositionPrior
from appliance.estimator.measurement import Measurement, measure, measured_on_grid
from appliance.estimator.noise import answer_covariance, learned_measurement, polished_fit, rival_fits
from appliance.estimator.posteriors import (
    SAME_ANSWER_CELLS,
    Answer,
    Posteriors,
    grid_answer,
    most_likely_fit,
    posteriors,
)
from appliance.estimator.refinement import CONVERGED_RMS, refined
from appliance.estimator.region import AMBIGUOUS_CELLS, MAX_OCCLUDED_SHARE, given_region, learned_region
from appliance.estimator.rescore import Plausible, Rescored, plausible_nodes, rescore_nodes
from appliance.estimator.skyline_grid import COARSE_STRIDE, SkylineGrid, nearest_node

#: Names the application's other layers import from here (the others are this module's own).
__all__ = ["AMBIGUOUS_CELLS", "COARSE_STRIDE", "EstimateResult", "FirstPass", "HEADING_TOLERANCE_DEG",
           "MIN_FIELD_OF_VIEW_DEG", "OCCLUSION_WEIGHT", "SAME_ANSWER_CELLS", "SIGMA_DEG", "SkylineGrid", "estimate",
           "first_pass", "measured_on_grid"]

#: The defaults, the same as the configuration's ([estimator] in appliance/config.py, a test keeps
#: them equal): the interval the search starts from (the estimate's is learned from the skyline), the
#: compass's tolerance, and the prior share of azimuths hidden by what the map lacks.
SIGMA_DEG = (0.3, 0.8)
HEADING_TOLERANCE_DEG = 4.0
OCCLUSION_WEIGHT = 0.05
#: The smallest field of view (deg of valid azimuths) a skyline must cover.
MIN_FIELD_OF_VIEW_DEG = 20.0

#: A search is made again with the sigma learned when its upper end lies below this share of the
#: search's lower end.
SEARCH_AGAIN_RATIO = 0.5
#: ... and with the occluders' share learned when the best fit leaves more than this many times the
#: prior share to them.
OCCLUSION_AGAIN_RATIO = 2.0
#: A search whose heading correction reached the compass's tolerance is made again with a tolerance
#: this much (deg) wider.
HEADING_WIDEN_DEG = 3.0
#: A best fit left with an RMS residual above this share of the search's lower sigma is poor: it is
#: searched again with the occluders' share at its most (MAX_OCCLUDED_SHARE), since a skyline raised by
#: trees the map lacks can be fitted, poorly, as terrain somewhere else ...
POOR_FIT_RATIO = 1.0
#: ... and with the interval narrowed to [NARROW_SHARE, 1] times that lower sigma: a wide interval weighs
#: every azimuth loosely, and a place whose skyline fits to a tenth of it can lose the search to one that
#: fits poorly everywhere.  The two best fits are compared with each one's occluded azimuths counted at
#: NARROW_CLIP times the first fit's RMS.
NARROW_SHARE = 1.0 / 3.0
NARROW_CLIP = 3.0
#: Neither search is made for a poor fit whose residuals are white: correlated less than NOISE_LIMITED_CORRELATION
#: from one azimuth to the next (:func:`confidence.lag_one_correlation`), at least NOISE_LIMITED_INDEPENDENT of them
#: independent (the likelihood's tempering, over every lag), and no more of the skyline left to occluders than the
#: prior share allows (OCCLUSION_AGAIN_RATIO).  What such a fit leaves is the sensor's white noise, which no other
#: place and no narrower interval fits more closely, and nothing stands above the map.  A wrong place, a residual
#: tilt, occluders and the map's error leave residuals that vary smoothly along the skyline (on the skylines those
#: searches are for, 0.6-0.9 and 0.04-0.24; on skylines with 0.5 deg of white noise, -0.15 to 0.22 and mostly 1).
NOISE_LIMITED_CORRELATION = 0.5
NOISE_LIMITED_INDEPENDENT = 0.5
#: What the notes of region.py say of a fit itself (not of rival places): a search made again at the same
#: place answers these with its own fit.
FIT_DOUBTS = ("poor match", "reaches the compass's tolerance", "covariance cannot be formed")


@dataclass(frozen=True)
class EstimateResult:
    """One position estimate.  Positions are fractional grid (row, col); the caller maps them to
    coordinates.  Posteriors are per node (best heading at each node)."""

    row: float
    col: float
    node: int
    heading_correction_deg: float
    lower: float
    upper: float
    log_lower: float
    region_nodes: np.ndarray
    region_area_m2: float
    log_lower_map: np.ndarray  # (n_nodes,) log lower posterior of each node's best heading
    log_upper_map: np.ndarray
    posterior_map: np.ndarray  # (n_nodes,) posterior at sigma's midpoint, marginal over heading
    rms_residual_deg: float
    n_valid: int
    sigma_deg: tuple[float, float]
    ambiguous: bool
    candidates: int
    elapsed_s: float
    notes: list[str] = field(default_factory=list)
    covariance_cells: np.ndarray | None = None  # (row, col) covariance of an exact fit (cells^2)
    #: The normalisers behind the maps above, in nats: log of the sum over every rescored candidate
    #: of its unnormalised lower and upper posterior (likelihood bound times prior), and of the
    #: midpoint posterior summed over heading.  The maps are normalised within this grid; searches
    #: over several grids (a tiled database) need these to normalise across them.
    log_evidence_lower: float = math.nan
    log_evidence_upper: float = math.nan
    log_evidence_mid: float = math.nan
    #: The best candidate's unnormalised log lower and upper posterior (nats), on the same scale.
    log_lower_unnormalised: float = math.nan
    log_upper_unnormalised: float = math.nan
    #: (n_nodes,) each node's unnormalised log upper posterior (its best heading), on the same scale;
    #: None when not made
    log_upper_unnormalised_map: np.ndarray | None = None
    #: how many nodes the first pass let through to be scored on every azimuth
    rescored: int = 0
    #: the answer's covariance (east, north; m^2) at sigma learned from the skyline; None without one
    covariance_m2: np.ndarray | None = None
    #: how many independent azimuths the skyline is worth (its residuals' autocorrelation)
    independent_azimuths: float = math.nan
    #: the credible region's nodes that belong to other modes than the answer's (rival places)
    rival_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    #: posterior share of the answer's mode and of the rival modes
    main_mass: float = math.nan
    rival_mass: float = 0.0
    #: the eye's height found by the exact fit above the map's surface under it (m), NaN without one
    eye_offset_m: float = math.nan
    #: whether sigma_deg was learned from the skyline (else it is the interval the search was given)
    sigma_learned: bool = False
    #: the share of the measured azimuths the best fit leaves to occluders (what the map lacks)
    occluded_share: float = 0.0
    #: whether the heading correction reached the compass's tolerance (then the answer is ambiguous)
    heading_at_limit: bool = False
    #: the sigma interval the search was made with (deg)
    sigma_deg_searched: tuple[float, float] = (math.nan, math.nan)
    #: the share of an independent azimuth each measured one counted for (1: as many as measured)
    temper: float = 1.0


def estimate(
    grid: SkylineGrid,
    azimuth_deg: np.ndarray,
    elevation_deg: np.ndarray,
    sigma_deg: tuple[float, float] = SIGMA_DEG,
    heading_tolerance_deg: float | None = HEADING_TOLERANCE_DEG,
    log_prior: np.ndarray | None = None,
    min_field_of_view_deg: float = MIN_FIELD_OF_VIEW_DEG,
    refine: bool = True,
    height_m: float | None = None,
    occlusion_weight: float = OCCLUSION_WEIGHT,
    weights: np.ndarray | None = None,
    map_sigma_m: float = 0.0,
    position_prior: PositionPrior | None = None,
    rescore_floor: float | None = None,
    first: FirstPass | None = None,
    learn_noise: bool = True,
    sigma_floor_deg: float | None = None,
    temper: float = 1.0,
    allowed_sigma_deg: float | None = None,
    polish: bool = False,
) -> EstimateResult:
    """Estimate the position from one skyline.

    ``heading_tolerance_deg`` = None means no compass: every heading is searched.  ``log_prior``
    is a per-node log prior (uniform in heading), e.g. from fusion; None is uniform.  ``height_m``
    is the camera's height above the map's surface for the exact refinement (default: the
    database's).  ``occlusion_weight`` is the prior share of azimuths hidden by something the map
    does not hold (trees, buildings): measurements above the prediction then cost at most
    :func:`likelihood.occlusion_cap_deg2`.  ``weights`` (0..1 per input azimuth: the detector's confidence, a
    mask) weigh the measurements.  ``map_sigma_m`` is the map's vertical error (1 sigma, metres):
    it adds (sigma_v / d)^2 to each azimuth's variance.  ``position_prior`` is the same belief as
    ``log_prior`` held in continuous form (a Gaussian in grid cells, e.g. a traverse's transported
    estimate): the exact fit between nodes weighs it, where the per-node prior cannot reach.
    ``rescore_floor`` is a first-pass lower log-posterior (unnormalised, nats) already reached on
    another part of the same lattice (:attr:`FirstPass.best_lower` on another tile): the nodes here are
    rescored only if they come within reach of it too, as one search over both parts would do.
    ``first`` is this skyline's :func:`first_pass` on this grid, made earlier (ValueError if it was
    made for another skyline or other arguments); None makes it here.  ``learn_noise`` (with an exact
    fit) replaces ``sigma_deg`` by the interval the best fit's residuals give and tempers the
    likelihood by the skyline's share of independent azimuths (``confidence.py``); ``sigma_deg`` then
    only steers the search.  A search over several grids keeps one sigma for all (False).
    ``sigma_floor_deg`` is the least sigma learned (the calibrated sensor's; None: the database's
    quantisation, ``confidence.SIGMA_FLOOR_DEG``).  ``temper`` (0 < temper <= 1, with ``learn_noise``
    False) is the share of an independent azimuth each measured one counts for, learned by an earlier
    search: a search over several grids made again at the noise its first round's answer left.
    ``allowed_sigma_deg`` is the most noise a fit may leave before the skyline is a poor match (None:
    the upper end of the interval searched); such a search's second round judges its fits by the
    interval its first round was given, not by the one learned from them.  ``polish`` (with
    ``learn_noise`` False) fits the best exact fit again from where it stands at the sigma given,
    with the head's residual tilt, as a search that learns the noise does at the noise learned: such
    a second round's answer and covariance are then those of one grid's search.

    When the best fit leaves far more of the skyline to occluders than ``occlusion_weight`` says (a
    forest's edge, buildings), the search is made once more with the share it found.  When the sigma
    learned lies far below the search's (a skyline far cleaner than the search assumed)
    but its best fit is not down to the floor (where nothing finer could be told apart), the search is
    made once more with the learned interval: a search that weighs every azimuth as loosely as the wide
    interval does can settle on a place that only the clean skyline tells apart.  The answer whose best
    fit leaves the smaller residual is kept.  A best fit that stays above the interval's lower end is
    searched again narrower (:func:`_narrowed`) and with half the skyline allowed to occluders
    (:func:`_occluders_checked`), unless its residuals are white noise (NOISE_LIMITED_CORRELATION,
    NOISE_LIMITED_INDEPENDENT).
    """
    t0 = time.perf_counter()
    search = _Search(heading_tolerance_deg=heading_tolerance_deg, log_prior=log_prior,
                     min_field_of_view_deg=min_field_of_view_deg, refine=refine, height_m=height_m,
                     occlusion_weight=occlusion_weight, weights=weights, map_sigma_m=map_sigma_m,
                     position_prior=position_prior, rescore_floor=rescore_floor, first=first,
                     learn_noise=learn_noise, sigma_floor_deg=sigma_floor_deg, temper=temper,
                     allowed_sigma_deg=allowed_sigma_deg, polish=polish)
    if not 0.0 < temper <= 1.0 or (learn_noise and temper != 1.0):
        raise ValueError(f"temper {temper}: expected 0 < temper <= 1, and 1 where the noise is learned here")
    again = learn_noise and first is None and rescore_floor is None
    res, fit = _estimate_with_fit(grid, azimuth_deg, elevation_deg, sigma_deg, search)
    lo, hi = res.sigma_deg
    at_floor = res.rms_residual_deg <= CONVERGED_RMS * search.floor_deg
    if again and res.sigma_learned and not at_floor and hi < SEARCH_AGAIN_RATIO * float(sigma_deg[0]):
        second, second_fit = _estimate_with_fit(grid, azimuth_deg, elevation_deg, (lo, 2.0 * hi), search)
        if second.rms_residual_deg <= res.rms_residual_deg:
            res, fit = second, second_fit
    elif again and res.sigma_learned and res.occluded_share > OCCLUSION_AGAIN_RATIO * occlusion_weight:
        # the occluders' share learned from the best fit (one step of EM on the occlusion mixture)
        search = replace(search, occlusion_weight=min(res.occluded_share, MAX_OCCLUDED_SHARE))
        res, fit = _estimate_with_fit(grid, azimuth_deg, elevation_deg, sigma_deg, search)
    # a poor fit that leaves white noise, and no more to occluders than the prior share allows (else
    # it was searched again for them above), is checked no further (NOISE_LIMITED_CORRELATION)
    noise_limited = (search.occlusion_weight == occlusion_weight
                     and res.occluded_share <= OCCLUSION_AGAIN_RATIO * occlusion_weight and _noise_limited(res, fit))
    if again and res.sigma_learned and _poor_fit(res, sigma_deg) and not noise_limited:
        # the narrower search's fits are judged poor against the interval given, as this one's are
        allowed = float(sigma_deg[1]) if search.allowed_sigma_deg is None else search.allowed_sigma_deg
        res = _narrowed(grid, azimuth_deg, elevation_deg, res, (NARROW_SHARE * float(sigma_deg[0]),
                                                                float(sigma_deg[0])),
                        replace(search, allowed_sigma_deg=allowed))
    if again and res.heading_at_limit and heading_tolerance_deg is not None:
        res = _widened(grid, azimuth_deg, elevation_deg, res, replace(search, heading_tolerance_deg=min(
            heading_tolerance_deg + HEADING_WIDEN_DEG, 180.0)))
        # the answer may now be another search's fit, whose residuals were not looked at
        noise_limited = False
    if (again and not res.ambiguous and search.occlusion_weight < MAX_OCCLUDED_SHARE and _poor_fit(res, sigma_deg)
            and not noise_limited):
        res = _occluders_checked(grid, azimuth_deg, elevation_deg, res,
                                 replace(search, occlusion_weight=MAX_OCCLUDED_SHARE))
    return replace(res, elapsed_s=time.perf_counter() - t0)


def _poor_fit(res: EstimateResult, sigma_deg: tuple[float, float]) -> bool:
    """Whether ``res``'s best fit stays above the noise the search assumed (POOR_FIT_RATIO)."""
    return res.rms_residual_deg > POOR_FIT_RATIO * float(sigma_deg[0])


def _noise_limited(res: EstimateResult, fit: Fit | None) -> bool:
    """Whether ``res``'s exact ``fit`` leaves white residuals: barely correlated from one azimuth to the
    next (NOISE_LIMITED_CORRELATION), and at least NOISE_LIMITED_INDEPENDENT of them independent (the
    noise learned from them); a sensor's white noise, not a wrong place or what the map lacks."""
    if fit is None or fit.residual_deg is None or not res.sigma_learned or res.temper < NOISE_LIMITED_INDEPENDENT:
        return False
    return confidence.lag_one_correlation(fit.residual_deg) < NOISE_LIMITED_CORRELATION


def _narrowed(grid: SkylineGrid, azimuth_deg: np.ndarray, elevation_deg: np.ndarray, res: EstimateResult,
              sigma_deg: tuple[float, float], search: _Search) -> EstimateResult:
    """``res``, whose best fit stays above the noise the search assumed, against the search made with
    the narrower ``sigma_deg``: the answer whose fit explains the skyline better, its confidence its
    own, except that rival places either search found stand: the narrower search's answer at
    ``res``'s place (SAME_ANSWER_CELLS) is ambiguous where ``res`` had rivals.  "Better": the mean
    squared residual with each fit's occluded azimuths counted at NARROW_CLIP times ``res``'s RMS, so
    that a fit does not win by leaving more of the skyline to occluders."""
    narrow = _estimate_once(grid, azimuth_deg, elevation_deg, sigma_deg, search)
    clip2 = (NARROW_CLIP * res.rms_residual_deg) ** 2

    def cost(r: EstimateResult) -> float:
        return (1.0 - r.occluded_share) * r.rms_residual_deg**2 + r.occluded_share * clip2

    moved = math.hypot(narrow.row - res.row, narrow.col - res.col)
    if cost(narrow) >= cost(res):
        if moved <= SAME_ANSWER_CELLS or narrow.rms_residual_deg >= res.rms_residual_deg:
            return res
        note = (f"ambiguous: searched with a narrower sigma, the skyline fits {moved:.0f} cells away more closely "
                f"with {narrow.occluded_share:.0%} of it left to occluders; what the map lacks decides where it is")
        return replace(res, ambiguous=True, notes=[*res.notes, note])
    if moved <= SAME_ANSWER_CELLS and res.rival_nodes.size:
        return _with_rivals(grid, narrow, res)
    return narrow


def _with_rivals(grid: SkylineGrid, answer: EstimateResult, earlier: EstimateResult) -> EstimateResult:
    """``answer``, a search made again at ``earlier``'s place, keeping the rival places ``earlier``
    found: their nodes (added to the region) and the notes saying so.  Doubts about ``earlier``'s own
    fit (FIT_DOUBTS) are the new fit's to answer."""
    doubts = [n for n in earlier.notes if n.startswith("ambiguous") and n not in answer.notes
              and not any(d in n for d in FIT_DOUBTS)]
    if not doubts:
        return answer
    added = np.setdiff1d(earlier.rival_nodes, answer.region_nodes)
    return replace(answer, ambiguous=True, rival_nodes=np.union1d(answer.rival_nodes, earlier.rival_nodes),
                   region_nodes=np.union1d(answer.region_nodes, added),
                   region_area_m2=answer.region_area_m2 + added.size * grid.dx_m * grid.dy_m,
                   notes=[*answer.notes, *doubts])


def _occluders_checked(grid: SkylineGrid, azimuth_deg: np.ndarray, elevation_deg: np.ndarray, res: EstimateResult,
                       search: _Search) -> EstimateResult:
    """``res``, whose best fit stays above the noise the search assumed, checked against the search
    that leaves as much of the skyline to occluders as ``search`` allows: the same place
    (SAME_ANSWER_CELLS) keeps ``res``, with the rival places that search found (:func:`_with_rivals`:
    places it fits as well once what the map lacks may hide part of the skyline); another place means
    what the map lacks (a forest's edge, a building) decides where the skyline was seen, and ``res`` is
    given, ambiguous."""
    hidden = _estimate_once(grid, azimuth_deg, elevation_deg, res.sigma_deg_searched, search)
    moved = math.hypot(hidden.row - res.row, hidden.col - res.col)
    if moved <= SAME_ANSWER_CELLS:
        return _with_rivals(grid, res, hidden) if hidden.rival_nodes.size else res
    note = (f"ambiguous: with {100 * search.occlusion_weight:.0f} % of the skyline allowed to stand above the map "
            f"(trees, buildings) the best place moves {moved:.0f} cells; what the map lacks decides where it is")
    return replace(res, ambiguous=True, notes=[*res.notes, note])


def _widened(grid: SkylineGrid, azimuth_deg: np.ndarray, elevation_deg: np.ndarray, res: EstimateResult,
             search: _Search) -> EstimateResult:
    """``res``, whose heading correction reached the compass's tolerance, searched again with the wider
    tolerance of ``search``: the same place (SAME_ANSWER_CELLS) with a heading inside the wider band is
    the answer; another place means the compass's tolerance decides where the skyline was seen, and the
    better fit of the two is given, ambiguous."""
    wide = _estimate_once(grid, azimuth_deg, elevation_deg, res.sigma_deg_searched, search)
    if math.hypot(wide.row - res.row, wide.col - res.col) <= SAME_ANSWER_CELLS:
        return _with_rivals(grid, wide, res)
    best = wide if wide.rms_residual_deg < res.rms_residual_deg else res
    note = ("ambiguous: with a wider compass tolerance the best place moves "
            f"{math.hypot(wide.row - res.row, wide.col - res.col):.0f} cells; the compass decides where it is")
    return replace(best, ambiguous=True, notes=[*best.notes, note])


@dataclass(frozen=True)
class _Search:
    """:func:`estimate`'s arguments beyond the skyline and sigma, for each of its searches."""

    heading_tolerance_deg: float | None
    log_prior: np.ndarray | None
    min_field_of_view_deg: float
    refine: bool
    height_m: float | None
    occlusion_weight: float
    weights: np.ndarray | None
    map_sigma_m: float
    position_prior: PositionPrior | None
    rescore_floor: float | None
    first: FirstPass | None
    learn_noise: bool
    sigma_floor_deg: float | None
    temper: float = 1.0
    allowed_sigma_deg: float | None = None
    polish: bool = False

    @property
    def floor_deg(self) -> float:
        """The least sigma learned: the calibrated sensor's, at least the database's quantisation."""
        return max(self.sigma_floor_deg or 0.0, confidence.SIGMA_FLOOR_DEG)


def first_pass(
    grid: SkylineGrid,
    azimuth_deg: np.ndarray,
    elevation_deg: np.ndarray,
    sigma_deg: tuple[float, float] = SIGMA_DEG,
    heading_tolerance_deg: float | None = HEADING_TOLERANCE_DEG,
    weights: np.ndarray | None = None,
    occlusion_weight: float = OCCLUSION_WEIGHT,
    map_sigma_m: float = 0.0,
    min_field_of_view_deg: float = MIN_FIELD_OF_VIEW_DEG,
) -> FirstPass:
    """The skyline's first pass over every node of ``grid`` (arguments as :func:`estimate`'s), to
    give :func:`estimate` later or to read its :attr:`FirstPass.best_lower`."""
    meas = measure(grid, azimuth_deg, elevation_deg, sigma_deg, weights, occlusion_weight, map_sigma_m,
                   min_field_of_view_deg)
    return scored_first_pass(grid, meas, heading_tolerance_deg)


@dataclass(frozen=True)
class _Found:
    """What one search found: its measurement, first pass and log prior (nats, per node), the nodes
    it found plausible and rescored, the posteriors, the answer, the exact fits made and the best of
    them (None without), the notes, and the share of itself the likelihood counts (1 until the noise
    is learned)."""

    meas: Measurement
    first: FirstPass
    lp: np.ndarray
    plausible: Plausible
    rescored: Rescored
    post: Posteriors
    answer: Answer
    fits: list[Fit]
    best_fit: Fit | None
    notes: list[str]
    temper: float = 1.0
    #: the best fit as the search made it, before it was polished at the learned sigma (None: not polished)
    unpolished_fit: Fit | None = None


def _estimate_once(grid: SkylineGrid, azimuth_deg: np.ndarray, elevation_deg: np.ndarray,
                   sigma_deg: tuple[float, float], search: _Search) -> EstimateResult:
    """One search and its confidence (:func:`estimate`'s arguments)."""
    return _estimate_with_fit(grid, azimuth_deg, elevation_deg, sigma_deg, search)[0]


def _estimate_with_fit(grid: SkylineGrid, azimuth_deg: np.ndarray, elevation_deg: np.ndarray,
                       sigma_deg: tuple[float, float], search: _Search) -> tuple[EstimateResult, Fit | None]:
    """One search and its confidence (:func:`estimate`'s arguments), and the exact fit its answer is
    (None without one)."""
    t0 = time.perf_counter()
    found = _searched(grid, azimuth_deg, elevation_deg, sigma_deg, search)
    searched = found.meas
    best_fit = found.best_fit
    learned = search.learn_noise and best_fit is not None and best_fit.residual_deg is not None
    if learned:
        found = _with_learned_noise(grid, found, search)
    elif search.polish and best_fit is not None:
        polished = polished_fit(grid, found.meas, best_fit, search.heading_tolerance_deg, search.height_m,
                                search.position_prior)
        if polished is not None:
            found = replace(found, best_fit=polished, answer=Answer(polished.row, polished.col, polished.heading_deg,
                                                                    polished.rms_deg, polished.covariance_cells))
    return _result(grid, found, searched, learned, search, t0), found.best_fit


def _searched(grid: SkylineGrid, azimuth_deg: np.ndarray, elevation_deg: np.ndarray,
              sigma_deg: tuple[float, float], search: _Search) -> _Found:
    """Steps 1 to 5 at the sigma interval given: the measurement, the first pass (the one given
    when there is one), the plausible nodes rescored, the posteriors, and the answer refined."""
    heading_tolerance_deg, log_prior, first = search.heading_tolerance_deg, search.log_prior, search.first
    meas = measure(grid, azimuth_deg, elevation_deg, sigma_deg, search.weights, search.occlusion_weight,
                   search.map_sigma_m, search.min_field_of_view_deg)
    given = first is not None
    if first is None:
        first = scored_first_pass(grid, meas, heading_tolerance_deg)
    elif not first.made_for(grid, meas, heading_tolerance_deg):
        raise ValueError("the first pass given was made for another grid, skyline or search")
    # a uniform prior is a read-only view of one zero, not an array of the grid's size
    lp = (np.broadcast_to(0.0, (grid.codes.shape[0],)) if log_prior is None
          else np.asarray(log_prior, dtype=np.float64))
    temper = search.temper
    if given and log_prior is None:
        # a first pass made earlier (a tiled search's floor) holds these bounds already; the
        # posteriors are made from them in place
        lo, up, scored = first.uniform_bounds()
        bounds = (lo.copy(), up.copy(), scored) if temper == 1.0 else (lo * temper, up * temper, scored)
    elif temper == 1.0:
        bounds = first_pass_bounds(first.scores, meas, lp)
    else:
        lo, up, scored = first_pass_bounds(first.scores, meas)
        bounds = (lo * temper + lp, up * temper + lp, scored)
    plausible = plausible_nodes(bounds, search.rescore_floor, temper)
    rescored = rescore_nodes(grid, meas, plausible.nodes, first.scores.shifts(plausible.nodes))
    post = posteriors(meas, lp, plausible, rescored, temper)
    answer = grid_answer(grid, meas, rescored, post)
    fits: list[Fit] = []
    best_fit: Fit | None = None
    notes: list[str] = []
    if search.refine:
        answer, fits, best_fit, notes = refined(grid, meas, lp, rescored, post, answer, heading_tolerance_deg,
                                                search.height_m, search.position_prior)
    return _Found(meas, first, lp, plausible, rescored, post, answer, fits, best_fit, notes, temper)


def _with_learned_noise(grid: SkylineGrid, found: _Found, search: _Search) -> _Found:
    """``found`` at the noise its best fit leaves (``noise.py``): the fits ranked again, the best one
    polished at the sigma learned, and the posteriors made again at that sigma, tempered."""
    floor, searched, lp, position_prior = search.floor_deg, found.meas, found.lp, search.position_prior
    assert found.best_fit is not None
    meas, temper = learned_measurement(searched, found.best_fit, floor)
    # the fits ranked again at the noise the skyline has: under the search's wide interval a
    # place that fits to the noise and one that fits ten times worse can look alike
    best_fit = most_likely_fit(found.fits, grid, lp, meas, position_prior)
    if best_fit is not found.best_fit:
        meas, temper = learned_measurement(searched, best_fit, floor)
    polished = polished_fit(grid, meas, best_fit, search.heading_tolerance_deg, search.height_m, position_prior)
    answer = found.answer
    unpolished = None
    if polished is not None:
        unpolished = best_fit
        best_fit = polished
        answer = Answer(polished.row, polished.col, polished.heading_deg, polished.rms_deg, polished.covariance_cells)
        meas, temper = learned_measurement(searched, best_fit, floor)
    # made between the search's parallel steps and the next search's, on this thread alone
    lo, up, scored = first_pass_bounds(found.first.scores, meas, serial=True)
    plausible = Plausible(found.plausible.nodes, lo * temper + lp, up * temper + lp, scored)
    post = posteriors(meas, lp, plausible, found.rescored, temper)
    return replace(found, meas=meas, plausible=plausible, post=post, answer=answer, best_fit=best_fit,
                   temper=temper, unpolished_fit=unpolished)


def _result(grid: SkylineGrid, found: _Found, searched: Measurement, learned: bool, search: _Search,
            t0: float) -> EstimateResult:
    """The estimate from what a search found: its rival fits, the posterior's modes, the answer's
    covariance and credible region (``region.py``); ``searched`` is the measurement as searched
    (sigma as given), ``t0`` when the search started (``time.perf_counter``)."""
    meas, post, answer, best_fit, temper = found.meas, found.post, found.answer, found.best_fit, found.temper
    def polish(fit: Fit) -> Fit | None:
        return polished_fit(grid, meas, fit, search.heading_tolerance_deg, search.height_m, search.position_prior)

    rivals = ([] if best_fit is None
              else rival_fits(found.fits, best_fit, grid, found.lp, meas, temper, search.position_prior,
                              found.unpolished_fit, polish))
    conf = confidence.modes(post.posterior_mid, grid.n_rows, grid.n_cols, answer.row, answer.col,
                            same_cells=SAME_ANSWER_CELLS)
    cov_cells = answer_covariance(best_fit, meas, temper, conf)
    if learned and np.all(np.isfinite(cov_cells)):
        # a place inside the answer's own 95 % ellipse is the answer's spread, not a rival
        reach = math.sqrt(confidence.chi2_2dof() * max(float(np.linalg.eigvalsh(cov_cells)[-1]), 0.0))
        if conf.rivals.size and reach > SAME_ANSWER_CELLS:
            conf = confidence.modes(post.posterior_mid, grid.n_rows, grid.n_cols, answer.row, answer.col,
                                    same_cells=SAME_ANSWER_CELLS, reach_cells=reach)
    answer_node = nearest_node(grid, answer.row, answer.col)
    cov_m2 = confidence.grid_to_east_north(cov_cells, grid.dx_m, grid.dy_m,
                                           float(grid.convergence_deg[answer_node]))
    fit_cells = [nearest_node(grid, f.row, f.col) for f in rivals]
    cell_area = grid.dx_m * grid.dy_m
    hidden = 0.0 if best_fit is None else best_fit.occluded / max(best_fit.n, 1)
    allowed = searched.sigma_hi_deg if search.allowed_sigma_deg is None else search.allowed_sigma_deg
    if learned:
        region = learned_region(conf, fit_cells, answer_node, cov_m2, cell_area, answer.heading_deg, answer.rms_deg,
                                allowed, hidden, bool(rivals), search.heading_tolerance_deg)
    else:
        region = given_region(post.region, fit_cells, answer_node, cell_area, answer.rms_deg, allowed,
                              hidden, bool(rivals))
    plausible = found.plausible
    return EstimateResult(
        row=answer.row, col=answer.col, node=post.best_node, heading_correction_deg=answer.heading_deg,
        lower=float(np.exp(post.best_log_lower)), upper=float(np.exp(post.best_log_upper)),
        log_lower=post.best_log_lower,
        region_nodes=region.nodes, region_area_m2=region.area_m2, log_lower_map=post.node_lower,
        log_upper_map=post.node_upper, posterior_map=post.posterior_mid, rms_residual_deg=answer.rms_deg,
        n_valid=meas.n_valid, sigma_deg=(meas.sigma_lo_deg, meas.sigma_hi_deg), ambiguous=region.ambiguous,
        candidates=plausible.scored_nodes * found.first.scores.band.size,
        elapsed_s=time.perf_counter() - t0, notes=found.notes + region.notes, covariance_cells=cov_cells,
        log_evidence_lower=post.log_sum_lo, log_evidence_upper=post.log_sum_up, log_evidence_mid=post.log_sum_mid,
        log_lower_unnormalised=post.best_lo_unnormalised, log_upper_unnormalised=post.best_up_unnormalised,
        log_upper_unnormalised_map=post.node_upper_unnormalised, rescored=int(plausible.nodes.size),
        covariance_m2=cov_m2, independent_azimuths=meas.n_eff * temper, rival_nodes=region.rival_nodes,
        main_mass=conf.main_mass, rival_mass=conf.rival_mass,
        eye_offset_m=math.nan if best_fit is None else best_fit.eye_offset_m, sigma_learned=learned,
        occluded_share=hidden, heading_at_limit=region.heading_at_limit,
        sigma_deg_searched=(searched.sigma_lo_deg, searched.sigma_hi_deg), temper=temper,
    )
