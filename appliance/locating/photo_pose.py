"""Any photo: its position and its orientation found together, from its skyline and a skyline database.

A photo's skyline is detected in its own pixels (:mod:`appliance.vision.photo`) and kept there, as
camera rays (:class:`PhotoView`).  Nothing of its orientation is assumed beyond what the user knows:

1. **Screening.**  The rays read through a level camera at yaw 0 give elevations at azimuths
   relative to the optical axis; every node of the search area is scored at every yaw of the
   database's azimuth step with the camera's pitch and roll as a linear nuisance
   (:func:`appliance.estimator.orientation.screen`), on the full skylines in one stage.  The
   panorama's first pass on skylines averaged over runs of azimuths leaves a photo's arc a dozen
   numbers, which many places match; and its parallax weighing, which counts each node's blur
   within its cell as noise independent from azimuth to azimuth, charges a node with near terrain
   for every azimuth of what is one shift of position (the best nodes are moved within their cells
   afterwards, :func:`_moved_within_cells`).  Both ranked the photo's own place out of the
   hypotheses.  The best distinct (node, yaw, tilt) triples are the hypotheses.  The tilt enters the
   screening linearly (an elevation offset of pitch times the cosine of the ray's azimuth from the axis, roll
   times its sine), which is exact only for a camera near level: at 7 deg of pitch over a 60-degree
   view its neglected second-order terms reach a third of a degree.  So when the orientation solved
   (step 2) at the hypothesis whose exact fit is best is tilted by more than RELEVEL_DEG, the first
   screening's best nodes (RESCREEN_SHARE of them) are screened again on the rays levelled through
   that pitch and roll, where the tilt left to it is small.
2. **Orientation on renders.**  At each hypothesis' place the skyline is rendered exactly (the ray
   march of the refinement) and yaw, pitch, roll and the focal length's correction are fitted to the
   detected pixels by robust least squares, the level's and the lens's tolerances as priors
   (:func:`solve_orientation`).  The hypotheses are ranked by how well those fits explain the photo
   (:func:`profiled_cauchy_nats`), not by the screening's or the exact fits' costs, which leave the
   focal length and the tilt's second order out.
3. **Position.**  The photo's skyline, carried to true azimuths and elevations through the best
   hypothesis' orientation, is located as any skyline is (:func:`appliance.locating.position.locate`,
   with a narrow heading tolerance: the yaw is known now, to a fraction of a degree), the orientation
   solved again at the answer, and the skyline located once more.  The estimate is free to move away
   from the hypothesis it started from, but only to a place that fits the photo at least as well with
   its own orientation solved there: where the place it moves to fits worse, the estimate is made again
   within CONFINE_CELLS of where it started (``kept_near`` in :func:`locate_photo`), the place it
   passed over is weighed as a rival, and the answer is not vouched for: the estimate's region, made
   within those cells, cannot show the places the whole area's estimate preferred.

The answer is ambiguous when the estimate says so, or when another hypothesis, at a place away
from the answer, fits the photo about as well with its own orientation: the estimate's region
is conditional on the orientation it was given, so rival orientations are weighed here.  Each
hypothesis is weighed twice: by its exact fit (the yaw nudged, the EXIF focal length), and with
its orientation and focal length solved on its render as the answer's are (:func:`refit_rivals`),
so that a place is not ruled out by a focal length or a tilt that the answer was given room for.
The second weighing is the fits' own robust likelihood (Cauchy) with its scale profiled out at
each place, counted for the skyline's independent azimuths less the six parameters each fit takes
from them (position, yaw, pitch, roll, focal length): a ratio of fits, not of costs at the noise
learned at the answer, which the hypotheses' cruder fits do not reach.  A hypothesis
inside the answer's own ellipse that fits clearly better than the answer also makes it
ambiguous: the answer is then not where the photo fits best.  So do places elsewhere that the
screening ranks above the answer's and that no hypothesis stood for (:func:`_screened_better`):
those were never weighed on renders.  And so does a skyline formed, over more than a third of the
view, by terrain within NEAR_SLOPE_CELLS of the answer (:func:`near_slope_share`): such a near
slope's skyline moves by tenths of a degree with its shape inside a cell, which the map does not
hold, so the fits that compare places cannot be trusted there.

Where the map ends close under a rendered horizon (the ray leaves it, or reaches its nodata, with
the ground there less than OPEN_RELIEF_M under the sightline), terrain beyond it may stand in the
photo's skyline: a ray above the render there costs no more than unseen terrain spread over
OPEN_SPAN_DEG would (:func:`one_sided`, :func:`profiled_cauchy_nats`).
"""

from __future__ import annotations

import importlib
import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from appliance.errors import InputError
from appliance.estimator import SkylineGrid, confidence
from appliance.estimator.estimate import MIN_FIELD_OF_VIEW_DEG
from appliance.estimator.exact import Fit, Model
from appliance.estimator.exact import refine as refine_exact
from appliance.estimator.likelihood import kernel_cap, occlusion_cap_deg2
from appliance.estimator.orientation import (
    Hypothesis,
    distinct_hypotheses,
    linearised_screen,
    relative_on_lattice,
    same_hypothesis,
    screen,
)
from appliance.estimator.raycast import edge_relief, render
from appliance.estimator.refinement import start_on_threads
from appliance.locating.position import Position, locate
from appliance.locating.search_grid import skyline_grid
from appliance.skyline import Skyline
from appliance.terrain.database import SkylineDatabase
from appliance.vision.camera import (
    CameraPose,
    enu_to_directions,
    pixels_to_rays,
    pose_from_world_from_camera,
    world_from_camera,
)
from appliance.vision.intrinsics import CameraIntrinsics
from appliance.vision.photo import PhotoSkyline, resample_photo

#: How many distinct hypotheses of the screening are fitted on renders.
HYPOTHESES = 20
#: The screening's measurement noise (deg): the parallax model's weights are made against it.
SCREEN_NOISE_DEG = 0.3
#: The screening fits every yaw of a node at once and again, one yaw at a time, at this many of its best
#: (``orientation.screen``'s ``kept_yaws``): the same answer as fitting every yaw one at a time, in a quarter the time.
SCREEN_KEPT_YAWS = 4
#: The screening's best nodes moved within their cells by the parallax model before the exact fits.
LINEARISED_NODES = 400
#: The first screening's best nodes screened again on levelled rays: this share of the search area's,
#: at least this many.
RESCREEN_SHARE = 0.25
RESCREEN_MIN = 2000
#: The exact fits of the hypotheses: their noise (deg), yaw freedom (deg) and tilt prior (deg, 1 sigma).
FIT_SIGMA_DEG = 0.3
HYPOTHESIS_YAW_DEG = 3.0
HYPOTHESIS_TILT_SIGMA_DEG = 2.5
#: The least arc (deg) of the photo's skyline that is located: the estimate's least field of view, and
#: one degree for the arc's ends, which the orientation moves by a fraction of a degree.
MIN_ARC_DEG = MIN_FIELD_OF_VIEW_DEG + 1.0
#: The rendered skyline's azimuth step (deg) for the orientation fit, and its margin beyond the view.
RENDER_STEP_DEG = 0.05
RENDER_MARGIN_DEG = 12.0
#: The orientation fits' robust loss: Cauchy, whose pull fades with the residual, so that a tree or a
#: cloud taken for terrain over a few degrees does not drag the fit (soft-L1's pull stays constant).
ROBUST_LOSS = "cauchy"
#: The orientation fit's measurement scale (deg): residuals beyond a few of these weigh less.
FIT_SCALE_DEG = 0.1
#: The photo's columns used by the orientation fit: about this many, evenly spread.
FIT_COLUMNS = 600
#: The joint fit of position and orientation and its covariance use this many of them (a render each).
JOINT_COLUMNS = 240
#: The heading tolerance (deg) of the estimates made with the solved yaw.
SOLVED_HEADING_TOLERANCE_DEG = 2.0
#: How far (cells) the joint fit of position and orientation may move the estimate's answer.
JOINT_REACH_CELLS = 3.0
#: The joint fit's finite-difference steps (relative, on parameters near 0 and near 1: absolute).
JOINT_STEP = 1e-2
#: The orientation's bounds: the level's tolerance plus this margin (deg), the focal length's this many sigmas.
BOUND_MARGIN_DEG = 1.0
BOUND_SIGMAS = 2.5
#: An orientation within this of its bound (deg; share of the focal length's bound) is at the bound.
AT_BOUND_DEG = 0.05
AT_BOUND_SHARE = 0.02
#: The screening and the hypotheses' fits are made again on the rays levelled through the orientation
#: solved at the best hypothesis when its pitch or roll is larger than this (deg): their tilt is linear,
#: whose neglected terms grow as its square (0.36 deg at 7 deg of pitch over a 60-degree view; 0.01 at 1).
RELEVEL_DEG = 1.0
#: A level camera looking north: the orientation the screening reads the rays through at first.
LEVEL = CameraPose(0.0, 0.0, 0.0)
#: The output skyline's azimuth step (deg).
SKYLINE_STEP_DEG = 0.25
#: Nodes within this many cells of the answer (or twice its 95 % radius) stand for the same place.
SAME_PLACE_CELLS = 2.5
#: An estimate that moved away from its hypothesis to a place that fits the photo worse is made again
#: within this many cells of where it started.
CONFINE_CELLS = 2.0 * SAME_PLACE_CELLS
#: A rival hypothesis within this many nats of the answer's fit makes the answer ambiguous; so do the
#: places beyond the answer's together, when the sum of their likelihood ratios exceeds exp(-RIVAL_NATS).
RIVAL_NATS = math.log(20.0)
#: Places more than this many nats behind the answer add nothing that counts to that sum (and are not
#: given a joint fit to see whether they are the answer's own slope).
ODDS_NATS = 3.0 * RIVAL_NATS
#: Residuals (deg) beyond which a column counts as an outlier in the rival comparison.
RIVAL_CLIP_DEG = 1.0
#: The refitted rivals' robust likelihood: the scale (deg) of its Cauchy density is profiled between
#: these (the database's quantisation; a residual this large is no fit), and a ray with no terrain
#: under it counts as this residual (the orientation fit's clip).
PROFILE_SCALE_DEG = (confidence.SIGMA_FLOOR_DEG, 3.0)
NO_TERRAIN_RESIDUAL_DEG = 30.0
#: The parameters a photo's fit takes from its skyline before what is left tells places apart: the
#: estimate's (position and heading) and the camera's pitch, roll and focal length.
PHOTO_FITTED_PARAMETERS = confidence.FITTED_PARAMETERS + 3
#: The photo's covariance is its fit's times this: on development photos (jacksboro, 60 deg, seeds 1-40)
#: the truth's squared Mahalanobis distance under the unscaled covariance had its 95th percentile at
#: 27 against chi-square's 5.99 (the truth inside the 95 % ellipse for 62 % of the right answers).
PHOTO_COVARIANCE_SCALE = 4.5

#: Terrain beyond the map's edge that rose this much (m) above the map's last height along a ray, a
#: hill or a moraine, would stand in the skyline there.  Where the map ends this close under the
#: rendered horizon, the photo's skyline may stand above the render and only its part below it
#: counts in full (:func:`one_sided`): a ridge past the edge is not evidence against the place.
OPEN_RELIEF_M = 50.0

#: The span of elevations (deg) over which such unseen terrain may lift the skyline, all alike: above
#: the render there the photo's skyline is never less likely than 1 / OPEN_SPAN_DEG per degree.  Not
#: more likely either: a place whose view runs off the map is not a place that fits.
OPEN_SPAN_DEG = 2.0

#: A skyline formed within this many cells of the camera is a near slope: it moves by tenths of a
#: degree with the slope's shape inside a cell, which the map resolves only at its nodes.  Where more
#: than NEAR_SLOPE_SHARE of the photo's skyline is such terrain at the answer, the fit is decided by
#: what the map cannot resolve, and the answer is not vouched for.
NEAR_SLOPE_CELLS = 10.0
NEAR_SLOPE_SHARE = 1.0 / 3.0


@dataclass(frozen=True)
class OrientationPrior:
    """What is known of the camera's orientation and lens before the photo is located.

    ``heading_deg``: the true azimuth of the optical axis (a compass, EXIF's GPSImgDirection), None
    when unknown; ``heading_tolerance_deg`` its bound.  ``pitch_tolerance_deg`` and
    ``roll_tolerance_deg``: how far from level the camera may be (the fits take half of each as a
    1-sigma prior).  ``focal_sigma``: the focal length's 1-sigma error as a fraction (0: known)."""

    heading_deg: float | None = None
    heading_tolerance_deg: float = 180.0
    pitch_tolerance_deg: float = 5.0
    roll_tolerance_deg: float = 3.0
    focal_sigma: float = 0.0

    def __post_init__(self) -> None:
        for name in ("heading_tolerance_deg", "pitch_tolerance_deg", "roll_tolerance_deg", "focal_sigma"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise InputError(f"{name} {value}: expected a finite value >= 0")
        if self.focal_sigma > 0.2:
            raise InputError(f"focal length uncertainty {self.focal_sigma:.0%} is above the 20 % this search handles")


@dataclass(frozen=True)
class PhotoView:
    """A photo's skyline in its own camera: the detected pixel (column, row) of each column, its
    confidence, and the lens."""

    intrinsics: CameraIntrinsics
    column_px: np.ndarray
    row_px: np.ndarray
    confidence: np.ndarray
    name: str = "photo"

    @classmethod
    def from_detection(cls, sky: PhotoSkyline, intrinsics: CameraIntrinsics, name: str = "photo") -> PhotoView:
        ok = np.isfinite(sky.row) & (sky.confidence > 0)
        cols = np.arange(sky.row.size, dtype=np.float64)
        return cls(intrinsics, cols[ok], np.asarray(sky.row, np.float64)[ok], np.asarray(sky.confidence)[ok], name)

    def arc_deg(self, step_deg: float = 1.0) -> float:
        """How wide an arc of azimuth (deg) the detected skyline covers, the camera held level: its
        samples on the lattice of ``step_deg`` (gaps left out), as the estimate counts them."""
        if self.column_px.size < 2:
            return 0.0
        az, el = directions(self.rays, CameraPose(0.0, 0.0, 0.0))
        lattice, _, _ = relative_on_lattice(np.mod(az + 180.0, 360.0) - 180.0, el, self.confidence, step_deg)
        return float(lattice.size * step_deg)

    @cached_property
    def rays(self) -> np.ndarray:
        """Camera-frame unit rays of the skyline's pixels (the lens's distortion removed)."""
        return pixels_to_rays(self.intrinsics, self.column_px, self.row_px)


def directions(rays: np.ndarray, pose: CameraPose, focal_scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(azimuth, elevation) in degrees of camera rays seen through ``pose``, the focal length
    multiplied by ``focal_scale`` (a longer lens narrows every ray's angle from the axis)."""
    r = np.array(rays, dtype=np.float64)
    if focal_scale != 1.0:
        r[..., :2] /= focal_scale * r[..., 2:3]
        r[..., 2] = 1.0
        r /= np.linalg.norm(r, axis=-1, keepdims=True)
    return enu_to_directions(r @ world_from_camera(pose).T)


#: The screening's best nodes: their indices, costs (deg^2) and yaws (deg).
Screened = tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class OrientationFit:
    """An orientation fitted at a place: the pose, the focal length's correction and the rms of the
    residuals within RIVAL_CLIP_DEG (deg)."""

    pose: CameraPose
    focal_scale: float
    rms_deg: float


@dataclass(frozen=True)
class PhotoAnswer:
    """The photo's position (the usual answer) with the orientation solved at it, the skyline as
    located, and the hypotheses weighed."""

    position: Position
    pose: CameraPose
    focal_px: float
    skyline: Skyline
    hypotheses: tuple[tuple[Hypothesis, Fit], ...]
    rivals: int

    def orientation_json(self) -> dict:
        return {"yaw_deg": round(self.pose.yaw_deg, 3), "pitch_deg": round(self.pose.pitch_deg, 3),
                "roll_deg": round(self.pose.roll_deg, 3), "focal_px": round(self.focal_px, 2)}


class _Renderer:
    """Exact skylines of a database's terrain at fractional nodes, over the photo's azimuths."""

    def __init__(self, grid: SkylineGrid, height_m: float) -> None:
        if grid.terrain is None:
            raise InputError("the database holds no terrain for exact renders; rebuild it with 'viper precompute'")
        self.grid, self.terrain, self.height_m = grid, grid.terrain, height_m
        self.dist = self.terrain.distances(min(grid.dx_m, grid.dy_m))

    def __call__(self, row: float, col: float, azimuth_deg: np.ndarray, eye_offset_m: float = 0.0) -> np.ndarray:
        return self.seen(row, col, azimuth_deg, eye_offset_m, edges=False)[0]

    def ranges(self, row: float, col: float, azimuth_deg: np.ndarray, eye_offset_m: float = 0.0) -> np.ndarray:
        """The range (m) of the rendered horizon at the true azimuths ``azimuth_deg``; NaN where no terrain."""
        return self._render(row, col, self._grid_azimuth(row, col, azimuth_deg), eye_offset_m)[1]

    def seen(self, row: float, col: float, azimuth_deg: np.ndarray, eye_offset_m: float = 0.0,
             edges: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """The render at the true azimuths ``azimuth_deg`` and, per azimuth, whether the map ends close
        under its horizon (within OPEN_RELIEF_M; all False without ``edges``)."""
        grid_az = self._grid_azimuth(row, col, azimuth_deg)
        el, _, ground = self._render(row, col, grid_az, eye_offset_m)
        if not edges or not math.isfinite(ground):
            return el, np.zeros(el.shape, dtype=bool)
        relief = edge_relief(self.terrain, self.grid.dx_m, self.grid.dy_m, row, col, grid_az, el,
                             ground + self.height_m + eye_offset_m)
        return el, relief < OPEN_RELIEF_M

    def _grid_azimuth(self, row: float, col: float, azimuth_deg: np.ndarray) -> np.ndarray:
        """True azimuths as the grid's, by the convergence at the node nearest (``row``, ``col``)."""
        node = min(max(int(round(row)), 0), self.grid.n_rows - 1) * self.grid.n_cols + min(
            max(int(round(col)), 0), self.grid.n_cols - 1)
        return azimuth_deg - float(self.grid.convergence_deg[node])

    def _render(self, row: float, col: float, grid_azimuth_deg: np.ndarray,
                eye_offset_m: float) -> tuple[np.ndarray, np.ndarray, float]:
        return render(self.terrain, self.grid.dx_m, self.grid.dy_m, row, col, grid_azimuth_deg, self.dist,
                      self.height_m + eye_offset_m)


def open_cap_deg(scale_deg: float) -> float:
    """The residual at which a Cauchy density of scale ``scale_deg`` falls to 1 / OPEN_SPAN_DEG per degree."""
    return scale_deg * math.sqrt(max(OPEN_SPAN_DEG / (math.pi * scale_deg) - 1.0, 0.0))


#: The least-squares fits' Cauchy scale (deg): their residuals in FIT_SCALE_DEG, their loss's f_scale 3.
LSQ_SCALE_DEG = 3.0 * FIT_SCALE_DEG


def one_sided(residual_deg: np.ndarray, open_sky: np.ndarray, scale_deg: float = LSQ_SCALE_DEG) -> np.ndarray:
    """Residuals (photo minus render, deg) for a Cauchy fit of scale ``scale_deg``, those above the
    render held at :func:`open_cap_deg` where the map ends close under the rendered horizon
    (``open_sky``): terrain beyond it may stand there, at any elevation over OPEN_SPAN_DEG."""
    return np.where(open_sky, np.minimum(residual_deg, open_cap_deg(scale_deg)), residual_deg)


#: The optimiser the orientation fits take their least squares from: its package imports all of scipy.optimize
#: (0.15 s), which the photo's first steps (detection, screening, the hypotheses' ray marches) do not need.
OPTIMIZER_MODULE = "scipy.optimize"


def start_loading_optimizer() -> threading.Thread:
    """Import OPTIMIZER_MODULE on a thread of its own, started: its import runs while the caller reads the
    photo, detects its skyline and screens the map (whose compiled kernels release the GIL), and the first
    orientation fit finds it loaded (or waits for it, as any second import of a module being imported
    does).  Returns the thread; a failed import is left to the fit's own import to report."""

    def load() -> None:
        try:
            importlib.import_module(OPTIMIZER_MODULE)
        except ImportError:
            pass

    thread = threading.Thread(target=load, name="viper-import")
    thread.start()
    return thread


def _fit_rays(view: PhotoView, count: int = FIT_COLUMNS) -> np.ndarray:
    """About ``count`` of the skyline's rays, evenly spread over its columns."""
    rays = view.rays
    if rays.shape[0] > count:
        rays = rays[np.linspace(0, rays.shape[0] - 1, count).round().astype(int)]
    return rays


def solve_orientation(rays: np.ndarray, rendered_az_deg: np.ndarray, rendered_el_deg: np.ndarray,
                      start: CameraPose, prior: OrientationPrior, start_scale: float = 1.0,
                      open_sky: np.ndarray | None = None) -> OrientationFit:
    """Yaw, pitch, roll and the focal length's correction that carry ``rays`` onto the rendered
    skyline (true azimuths ``rendered_az_deg``, increasing, unwrapped; NaN where no terrain), from
    ``start``; robust (Cauchy), with the prior's tolerances as Gaussian priors.  ``open_sky``: per
    rendered azimuth, where the map ends close under the horizon (:func:`one_sided`)."""
    az0 = float(rendered_az_deg[0])
    ok_render = np.isfinite(rendered_el_deg)
    fill = np.where(ok_render, rendered_el_deg, -90.0)
    open_share = np.zeros(rendered_el_deg.shape) if open_sky is None else np.asarray(open_sky, dtype=np.float64)
    use_scale = prior.focal_sigma > 0.0

    def pose_of(p: np.ndarray) -> tuple[CameraPose, float]:
        return CameraPose(float(p[0]), float(p[1]), float(p[2])), float(math.exp(p[3])) if use_scale else 1.0

    def residual_deg(p: np.ndarray) -> np.ndarray:
        pose, scale = pose_of(p)
        az, el = directions(rays, pose, scale)
        rel = np.mod(az - az0, 360.0) + az0
        pred = np.interp(rel, rendered_az_deg, fill, left=-90.0, right=-90.0)
        return one_sided(np.asarray(el - pred), np.interp(rel, rendered_az_deg, open_share) > 0.5)

    def residuals(p: np.ndarray) -> np.ndarray:
        res = np.clip(residual_deg(p), -30.0, 30.0) / FIT_SCALE_DEG
        return np.concatenate([res, _prior_terms(prior, p[0], p[1], p[2], p[3])])

    from scipy.optimize import least_squares  # here, not at import: see start_loading_optimizer

    p_hi, r_hi, s_hi = _bounds(prior)
    lower = np.array([start.yaw_deg - 180.0, -p_hi, -r_hi, -s_hi])
    upper = np.array([start.yaw_deg + 180.0, p_hi, r_hi, s_hi])
    p0 = np.clip(np.array([start.yaw_deg, start.pitch_deg, start.roll_deg, math.log(start_scale)]),
                 lower + 1e-9, upper - 1e-9)
    fit = least_squares(residuals, p0, loss=ROBUST_LOSS, f_scale=3.0, x_scale=np.array([0.5, 0.5, 0.5, 0.01]),
                        bounds=(lower, upper), method="trf", max_nfev=200)
    pose, scale = pose_of(fit.x)
    pose = CameraPose(pose.yaw_deg % 360.0, pose.pitch_deg, pose.roll_deg)
    e = residual_deg(fit.x)
    inliers = np.abs(e) < RIVAL_CLIP_DEG
    rms = float(np.sqrt(np.mean(e[inliers] ** 2))) if inliers.any() else math.inf
    return OrientationFit(pose, scale, rms)


def _prior_terms(prior: OrientationPrior, yaw_deg: float, pitch_deg: float, roll_deg: float,
                 log_scale: float) -> np.ndarray:
    """The orientation's priors as residuals in sigmas: half of each tolerance is one sigma (the focal
    length's only when it is free, the heading's only when there is one)."""
    terms = [pitch_deg / max(prior.pitch_tolerance_deg / 2.0, 1e-3),
             roll_deg / max(prior.roll_tolerance_deg / 2.0, 1e-3)]
    if prior.focal_sigma > 0.0:
        terms.append(log_scale / prior.focal_sigma)
    if prior.heading_deg is not None and prior.heading_tolerance_deg < 180.0:
        turn = (yaw_deg - prior.heading_deg + 180.0) % 360.0 - 180.0
        terms.append(turn / max(prior.heading_tolerance_deg / 2.0, 1e-3))
    return np.asarray(terms)


def _bounds(prior: OrientationPrior) -> tuple[float, float, float]:
    """The bounds of |pitch|, |roll| (deg) and |log focal scale| of the fits."""
    return (prior.pitch_tolerance_deg + BOUND_MARGIN_DEG, prior.roll_tolerance_deg + BOUND_MARGIN_DEG,
            max(BOUND_SIGMAS * prior.focal_sigma, 1e-6))


def _rendered_view(render_at: _Renderer, row: float, col: float, rays: np.ndarray, pose: CameraPose,
                   scale: float, eye_offset_m: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rendered skyline over the photo's view at ``pose``, with a margin for the fit to move in,
    and where the map ends close under it (:meth:`_Renderer.seen`)."""
    az, _ = directions(rays, pose, scale)
    a0 = float(az[0])
    rel = np.mod(az - a0 + 180.0, 360.0) - 180.0
    lo, hi = float(rel.min()) - RENDER_MARGIN_DEG, float(rel.max()) + RENDER_MARGIN_DEG
    grid_az = a0 + np.arange(lo, hi + RENDER_STEP_DEG, RENDER_STEP_DEG)
    return grid_az, *render_at.seen(row, col, np.mod(grid_az, 360.0), eye_offset_m)


def refine_jointly(render_at: _Renderer, rays: np.ndarray, row: float, col: float, eye_offset_m: float,
                   pose: CameraPose, scale: float, prior: OrientationPrior) -> tuple[CameraPose, float]:
    """Position (fractional node) and orientation fitted together on exact renders at the rays'
    own azimuths, from the estimate's answer: alternating the two crawls along the valley where a
    yaw, a focal length and a move trade against each other.  Robust (Cauchy), the tolerances as
    bounds and priors; the move is bounded to JOINT_REACH_CELLS.  Returns the orientation (the
    estimate then places the camera with it)."""
    _, _, pose, scale = fit_jointly(render_at, rays, row, col, eye_offset_m, pose, scale, prior)
    return pose, scale


def fit_jointly(render_at: _Renderer, rays: np.ndarray, row: float, col: float, eye_offset_m: float,
                pose: CameraPose, scale: float, prior: OrientationPrior) -> tuple[float, float, CameraPose, float]:
    """:func:`refine_jointly`'s fit: the place it moved to (fractional row, column) and the orientation."""
    use_scale = prior.focal_sigma > 0.0

    # parameters: moves from the start (rows, columns, yaw in deg), then pitch, roll and log focal scale
    def residuals(p: np.ndarray) -> np.ndarray:
        moved = np.array([row + p[0], col + p[1], pose.yaw_deg + p[2], p[3], p[4], p[5] if use_scale else 0.0])
        res = np.clip(np.nan_to_num(_joint_residual_deg(render_at, rays, moved, eye_offset_m), nan=30.0), -30.0, 30.0)
        return np.concatenate([res / FIT_SCALE_DEG, _prior_terms(prior, pose.yaw_deg + p[2], p[3], p[4], p[5])])

    from scipy.optimize import least_squares  # here, not at import: see start_loading_optimizer

    p_hi, r_hi, s_hi = _bounds(prior)
    reach = JOINT_REACH_CELLS
    lower = np.array([-reach, -reach, -10.0, -p_hi, -r_hi, -s_hi])
    upper = np.array([reach, reach, 10.0, p_hi, r_hi, s_hi])
    p0 = np.clip(np.array([0.0, 0.0, 0.0, pose.pitch_deg, pose.roll_deg, math.log(scale)]), lower + 1e-9,
                 upper - 1e-9)
    fit = least_squares(residuals, p0, loss=ROBUST_LOSS, f_scale=3.0, bounds=(lower, upper), method="trf",
                        x_scale=np.array([0.2, 0.2, 0.1, 0.1, 0.1, 0.005]), diff_step=JOINT_STEP, max_nfev=60)
    x = fit.x
    return row + float(x[0]), col + float(x[1]), CameraPose((pose.yaw_deg + float(x[2])) % 360.0, float(x[3]),
                                                            float(x[4])), (float(math.exp(x[5])) if use_scale else 1.0)


def _joint_residual_deg(render_at: _Renderer, rays: np.ndarray, p: np.ndarray, eye_offset_m: float) -> np.ndarray:
    """Each ray's elevation through the orientation of ``p`` (row, col, yaw, pitch, roll, log focal
    scale) minus the skyline rendered from (row, col) at the ray's own azimuth; NaN where no terrain."""
    az, el = directions(rays, CameraPose(float(p[2]), float(p[3]), float(p[4])), float(math.exp(p[5])))
    rendered, open_sky = render_at.seen(float(p[0]), float(p[1]), az, eye_offset_m)
    return one_sided(np.asarray(el - rendered), open_sky)


def world_skyline(view: PhotoView, pose: CameraPose, scale: float, step_deg: float = SKYLINE_STEP_DEG) -> Skyline:
    """The photo's skyline in true azimuths and elevations through ``pose``, on a regular azimuth grid."""
    az, el = directions(view.rays, pose, scale)
    order = np.argsort(np.mod(az - az[0] + 180.0, 360.0) - 180.0, kind="stable")
    sky = PhotoSkyline(view.row_px[order], az[order], el[order], view.confidence[order], ())
    return resample_photo(sky, step_deg)


def locate_photo(db: SkylineDatabase, view: PhotoView, prior: OrientationPrior, *,
                 sigma_deg: tuple[float, float], log_prior: np.ndarray | None = None,
                 height_m: float | None = None, occlusion_weight: float = 0.05, map_sigma_m: float = 0.0,
                 sigma_floor_deg: float | None = None) -> PhotoAnswer:
    """The photo's position and orientation on ``db``: screening, exact fits at the best hypotheses,
    the orientation on renders, then the estimate with the solved orientation (module docstring).
    ``log_prior``: per node, -inf outside the search area.  ``sigma_deg``, ``height_m``,
    ``occlusion_weight``, ``map_sigma_m`` and ``sigma_floor_deg`` are the estimate's."""
    grid = skyline_grid(db)
    h_m = db.height_m if height_m is None else height_m
    render_at = _Renderer(grid, h_m)
    if view.column_px.size < 2:
        raise InputError(f"{view.name}: no skyline found (no column shows sky above ground)")
    rays = view.rays
    step = grid.az_step_deg
    level = LEVEL
    lattice, _, _ = _levelled_lattice(rays, view.confidence, level, step)
    if lattice.size * step < MIN_ARC_DEG:
        raise InputError(f"{view.name}: the skyline spans {lattice.size * step:.0f} deg of the view, less than the "
                         f"{MIN_ARC_DEG:.0f} deg needed to locate a photo")
    usable = np.isfinite(grid.offset_deg)
    nodes = np.flatnonzero(usable if log_prior is None else usable & np.isfinite(log_prior))
    if nodes.size == 0:
        raise InputError("no node of the database lies inside the search area")

    fit_rays = _fit_rays(view)
    # places the estimate moved to and was taken back from (they fit worse than where it started): row, col, nats
    passed: list[tuple[float, float, float]] = []

    def weighed(found: list[tuple[Hypothesis, Fit]], level: CameraPose, first: tuple[OrientationFit, float] | None,
                ) -> tuple[list[tuple[Hypothesis, Fit]], list[tuple[OrientationFit, float]]]:
        """The hypotheses and their orientations solved on their renders (:func:`_refit`; ``first``:
        the first one's, made already), ranked by those fits' nats, best first."""
        # each hypothesis' orientation on its own: on the kernels' threads (mostly ray marches, which release the GIL)
        refits = start_on_threads(lambda hf: _refit(render_at, fit_rays, hf, prior, level),
                                  found if first is None else found[1:])()
        if first is not None:
            refits = [first, *refits]
        order = sorted(range(len(found)), key=lambda i: -_finite_or_lowest(refits[i][1]))
        return [found[i] for i in order], [refits[i] for i in order]

    def located(sky: Skyline, area: np.ndarray | None) -> Position:
        return locate(db, sky, sigma_deg, SOLVED_HEADING_TOLERANCE_DEG, log_prior=area, grid=grid, height_m=h_m,
                      occlusion_weight=occlusion_weight, map_sigma_m=map_sigma_m, sigma_floor_deg=sigma_floor_deg,
                      source=view.name)

    def kept_near(pos: Position, sky: Skyline, area: np.ndarray | None, row: float, col: float,
                  nats: Callable[[], float], pose: CameraPose, scale: float) -> tuple[Position, np.ndarray | None]:
        """``pos``, or, where it lies beyond the same place from (``row``, ``col``) and fits the photo
        worse than ``nats()`` there with its orientation solved from ``pose`` and ``scale``, the estimate
        made again within CONFINE_CELLS of (``row``, ``col``): the position and the search area it was
        made in."""
        res = pos.result
        if math.hypot(res.row - row, res.col - col) <= SAME_PLACE_CELLS:
            return pos, area
        eye = res.eye_offset_m if math.isfinite(res.eye_offset_m) else 0.0
        turned = CameraPose(pose.yaw_deg + res.heading_correction_deg, pose.pitch_deg, pose.roll_deg)
        there = _solved_nats(render_at, fit_rays, res.row, res.col, turned, scale, eye, prior)[1]
        if there >= nats():
            return pos, area
        passed.append((res.row, res.col, there))
        confined = _confined(grid, area, row, col, CONFINE_CELLS)
        return located(sky, confined), confined

    screened, found, ranked = _screen_and_fit(grid, rays, view.confidence, level, nodes, prior, h_m,
                                              occlusion_weight, map_sigma_m)
    if found is None:
        raise InputError(f"{view.name}: no node of the search area sees terrain over the photo's view")
    if not found:
        raise InputError(f"{view.name}: no place of the search area fits the photo's skyline")
    # the orientation at the exact fits' best decides whether the rays are levelled and screened again
    exact_best = _refit(render_at, fit_rays, found[0], prior, level)
    first: tuple[OrientationFit, float] | None = exact_best
    tilt = exact_best[0].pose
    if max(abs(tilt.pitch_deg), abs(tilt.roll_deg)) > RELEVEL_DEG:
        # the screening's linear tilt is good near level only: screen again with the rays levelled, the
        # nodes the first screening ranked best (the tilt's second order moves a place's cost little)
        relevel = CameraPose(0.0, tilt.pitch_deg, tilt.roll_deg)
        again = ranked[: max(RESCREEN_MIN, int(RESCREEN_SHARE * nodes.size))]
        screened_again, found_again, _ = _screen_and_fit(grid, rays, view.confidence, relevel, again, prior, h_m,
                                                         occlusion_weight, map_sigma_m)
        if found_again:
            level, screened, found, first = relevel, screened_again, found_again, None
    fits, refits = weighed(found, level, first)
    solved = refits[0][0]
    pose, scale = solved.pose, solved.focal_scale
    sky = world_skyline(view, pose, scale)
    best = fits[0][1]
    best_nats = refits[0][1]
    pos, area = kept_near(located(sky, log_prior), sky, log_prior, best.row, best.col, lambda: best_nats, pose, scale)
    res = pos.result
    eye = res.eye_offset_m if math.isfinite(res.eye_offset_m) else 0.0
    turned = CameraPose(pose.yaw_deg + res.heading_correction_deg, pose.pitch_deg, pose.roll_deg)
    joint_rays = _fit_rays(view, JOINT_COLUMNS)
    pose, scale = refine_jointly(render_at, joint_rays, res.row, res.col, eye, turned, scale, prior)
    first_row, first_col, first_eye, joint_pose, joint_scale = res.row, res.col, eye, pose, scale

    def at_first() -> float:
        return _nats_at(render_at, fit_rays, first_row, first_col, joint_pose, joint_scale, first_eye)

    sky = world_skyline(view, pose, scale)
    pos, _ = kept_near(located(sky, area), sky, area, first_row, first_col, at_first, pose, scale)
    res = pos.result
    eye = res.eye_offset_m if math.isfinite(res.eye_offset_m) else eye
    pose = CameraPose((pose.yaw_deg + res.heading_correction_deg) % 360.0, pose.pitch_deg, pose.roll_deg)
    pos = _with_joint_covariance(pos, grid, render_at, joint_rays, pose, scale, prior, eye)
    same = _same_place_cells(pos, grid)
    rivals = _rivals(pos, fits, grid, same)
    notes = []
    if rivals:
        notes.append(f"{rivals} other place(s) fit the photo about as well with another orientation "
                     f"(within {RIVAL_NATS:.1f} nats)")
    refit = refit_rivals(render_at, fit_rays, fits, pos, grid, pose, scale, eye, prior, same, level, refits, passed)
    if refit.crowded and not refit.rivals:
        share, share_max = (o / (1.0 + o) for o in (refit.odds_elsewhere, math.exp(-RIVAL_NATS)))
        notes.append(f"the other places weighed, each with its own orientation and focal length solved, together "
                     f"hold {share:.0%} of the posterior (a clear answer leaves them {share_max:.0%} at most): the "
                     "answer is the best of them, not clear of them")
    if refit.rivals:
        notes.append(f"{refit.rivals} other place(s) fit the photo about as well with their own orientation and "
                     f"focal length solved (within {RIVAL_NATS:.1f} nats of the answer)")
    if refit.better:
        notes.append(f"{refit.better} place(s) inside the answer's ellipse, more than {SAME_PLACE_CELLS:g} cells "
                     f"from it, fit the photo better than the answer by more than {RIVAL_NATS:.1f} nats: the "
                     "answer is not where the photo fits best")
    rivals += max(refit.rivals, int(refit.crowded))
    if passed:
        moved_m = max(math.hypot((r - res.row) * grid.dy_m, (c - res.col) * grid.dx_m) for r, c, _ in passed)
        notes.append(f"the estimate over the whole search area went {moved_m:.0f} m from here, to a place that fits "
                     "the photo worse with its own orientation solved there: the two weighings disagree, the answer "
                     "is not vouched for")
    near = near_slope_share(render_at, fit_rays, res.row, res.col, pose, scale, eye)
    if near > NEAR_SLOPE_SHARE:
        notes.append(f"{near:.0%} of the photo's skyline is terrain within "
                     f"{NEAR_SLOPE_CELLS * min(grid.dx_m, grid.dy_m):.0f} m of the answer: the map resolves such "
                     "near slopes only at its nodes, too coarsely to vouch for the place")
    limit = _at_tolerance(pose, scale, prior)
    if limit:
        notes.append(f"the {limit} reached the tolerance given: the fit is forced there, the answer is not vouched for")
    unseen = _screened_better(grid, pos, screened, same, [h for h, _ in fits])
    if unseen:
        notes.append(f"{unseen} node(s) elsewhere screen at least as well as the answer's; the photo's view "
                     "does not rule them out")
    if notes:
        pos = replace(pos, estimate=replace(pos.result, ambiguous=True, notes=[*pos.result.notes, *notes]))
    pos = _widened_covariance(pos)
    return PhotoAnswer(pos, pose, view.intrinsics.fx * scale, sky, tuple(fits), rivals)


def near_slope_share(render_at: _Renderer, rays: np.ndarray, row: float, col: float, pose: CameraPose, scale: float,
                     eye_offset_m: float) -> float:
    """The share of the rays whose rendered horizon at (``row``, ``col``), seen with ``pose`` and focal
    ``scale``, lies within NEAR_SLOPE_CELLS cells."""
    az, _ = directions(rays, pose, scale)
    far = render_at.ranges(row, col, np.mod(az, 360.0), eye_offset_m)
    near_m = NEAR_SLOPE_CELLS * min(render_at.grid.dx_m, render_at.grid.dy_m)
    return float(np.mean(np.isfinite(far) & (far < near_m))) if far.size else 0.0


def _widened_covariance(pos: Position) -> Position:
    """The answer with its covariance times PHOTO_COVARIANCE_SCALE (what the residuals do not carry:
    the position's trade against the yaw and the focal length beyond the linear model, the clouds'
    and the near objects' correlated error)."""
    cov = pos.result.covariance_m2
    if cov is None:
        return pos
    return replace(pos, estimate=replace(pos.result, covariance_m2=PHOTO_COVARIANCE_SCALE * np.asarray(cov)))


def _moved_within_cells(grid: SkylineGrid, nodes: np.ndarray, yaw: np.ndarray, tilt: np.ndarray,
                        lattice: np.ndarray, m: np.ndarray, w: np.ndarray, prior: OrientationPrior,
                        occlusion_weight: float, map_sigma_m: float,
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The screening's best nodes scored again with each one's skyline moved within its cell by the
    parallax model and the tilt refined (``orientation.linearised_screen``): the nodes, their new
    costs, yaws and tilts."""
    assert grid.distance_codes is not None
    half = 0.5 * max(grid.dx_m, grid.dy_m)
    sigma = max(prior.pitch_tolerance_deg, prior.roll_tolerance_deg) / 2.0
    cap = kernel_cap(occlusion_cap_deg2(occlusion_weight, SCREEN_NOISE_DEG))
    moved, delta = linearised_screen(grid.codes, grid.distance_codes, grid.offset_deg, grid.step_deg,
                                     grid.ground_gradient_at(nodes), grid.convergence_deg, nodes, yaw, tilt, lattice,
                                     m, w, grid.rho2_m2, grid.inverse_range2, half, SCREEN_NOISE_DEG, sigma, cap,
                                     map_sigma_m)
    return nodes, moved, np.mod(yaw + delta[:, 2], 360.0), tilt + delta[:, 4:6]


def _exact_hypotheses(grid: SkylineGrid, hyps: list[Hypothesis], lattice: np.ndarray, m: np.ndarray,
                      w: np.ndarray, height_m: float, occlusion_weight: float,
                      map_sigma_m: float) -> list[tuple[Hypothesis, Fit]]:
    """Each hypothesis fitted between nodes on exact renders (position, yaw, eye height and the
    tilt), best first by the fit's cost per measured azimuth (the occluded ones at the cap)."""
    assert grid.terrain is not None
    n_az = grid.n_azimuths
    cap = occlusion_cap_deg2(occlusion_weight, FIT_SIGMA_DEG)

    def fitted(h: Hypothesis) -> Fit | None:
        assert grid.terrain is not None
        shift = int(round(h.yaw_deg / grid.az_step_deg))
        measured = np.full(n_az, np.nan)
        weights = np.zeros(n_az)
        idx = np.mod(lattice + shift, n_az)
        u = np.radians(lattice * grid.az_step_deg)
        # the screening's tilt taken out: the exact fit starts level and fits what is left
        measured[idx], weights[idx] = m - h.t1_deg * np.cos(u) - h.t2_deg * np.sin(u), w
        r, c = divmod(h.node, grid.n_cols)
        return refine_exact(grid.terrain, grid.dx_m, grid.dy_m, measured, r, c, grid.n_cols, 0.0, height_m,
                            sigma_deg=FIT_SIGMA_DEG, heading_bounds_deg=(-HYPOTHESIS_YAW_DEG, HYPOTHESIS_YAW_DEG),
                            model=Model(weights, cap, map_sigma_m), tilt_sigma_deg=HYPOTHESIS_TILT_SIGMA_DEG)

    out: list[tuple[Hypothesis, Fit]] = []
    # each hypothesis fitted on its own: on the kernels' threads (mostly ray marches, which release the GIL)
    for h, fit in zip(hyps, start_on_threads(fitted, hyps)()):
        if fit is not None and fit.n > 0:
            out.append((h, replace(fit, ssd=fit.ssd + fit.occluded * kernel_cap(cap))))
    out.sort(key=lambda hf: hf[1].ssd / hf[1].n)
    return out


def _pose_of_fit(h: Hypothesis, fit: Fit, level: CameraPose = LEVEL) -> CameraPose:
    """The camera's orientation a hypothesis' exact fit gives: the yaw turned by the fit's heading,
    pitch and roll from its tilt (the tilt's terms turned into the camera's axes), and composed with
    ``level`` (yaw 0), the pitch and roll the rays were levelled through before the screening."""
    yaw = h.yaw_deg + fit.heading_deg
    psi = math.radians(yaw)
    t1, t2 = fit.tilt_deg
    along = h.t1_deg + t1 * math.cos(psi) + t2 * math.sin(psi)
    across = h.t2_deg - t1 * math.sin(psi) + t2 * math.cos(psi)
    pose = CameraPose(yaw % 360.0, -along, across)
    if level.pitch_deg == 0.0 and level.roll_deg == 0.0:
        return pose
    # rays seen through `level` are a level camera's rays L^T M r: the camera's rotation is W(pose) L^T M
    rotation = world_from_camera(pose) @ world_from_camera(CameraPose()).T @ world_from_camera(level)
    return pose_from_world_from_camera(rotation)


def _levelled_lattice(rays: np.ndarray, confidence: np.ndarray, level: CameraPose,
                      step_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rays' elevations on the lattice of azimuths (relative to the axis, ``step_deg``) seen through
    ``level`` (yaw 0): :func:`appliance.estimator.orientation.relative_on_lattice`'s lattice, elevations
    and weights."""
    rel_az, rel_el = directions(rays, level)
    return relative_on_lattice(np.mod(rel_az + 180.0, 360.0) - 180.0, rel_el, confidence, step_deg)


def _screen_and_fit(grid: SkylineGrid, rays: np.ndarray, confidence: np.ndarray, level: CameraPose,
                    nodes: np.ndarray, prior: OrientationPrior, height_m: float, occlusion_weight: float,
                    map_sigma_m: float) -> tuple[Screened, list[tuple[Hypothesis, Fit]] | None, np.ndarray]:
    """Step 1 of the module docstring on the rays levelled through ``level``: the screening of
    ``nodes`` at every yaw (its LINEARISED_NODES best nodes, moved within their cells, with their
    costs and yaws, for :func:`_screened_better`), the distinct hypotheses fitted on exact renders, best
    first by those fits (None when no node sees terrain over the view, empty when no fit succeeds), and
    the nodes that see it, best first by the screening."""
    step = grid.az_step_deg
    lattice, m, w = _levelled_lattice(rays, confidence, level, step)
    yaw_bounds = None
    if prior.heading_deg is not None and prior.heading_tolerance_deg < 180.0:
        yaw_bounds = (prior.heading_deg, prior.heading_tolerance_deg + step)
    tilt_bounds = (prior.pitch_tolerance_deg + 1.0, prior.roll_tolerance_deg + 1.0)
    # one stage, on the full skylines, without the parallax weighing (the module docstring, step 1)
    cost, yaw, tilt = screen(grid.codes, grid.offset_deg, grid.step_deg, nodes, lattice, m, w, tilt_bounds,
                             noise_deg=SCREEN_NOISE_DEG, yaw_deg=yaw_bounds, kept_yaws=SCREEN_KEPT_YAWS)
    order = np.argsort(cost, kind="stable")
    order = order[np.isfinite(cost[order])]
    ranked = nodes[order]
    best = order[:LINEARISED_NODES]
    found, cost, yaw, tilt = nodes[best], cost[best], yaw[best], tilt[best]
    if grid.has_parallax:
        found, cost, yaw, tilt = _moved_within_cells(grid, found, yaw, tilt, lattice, m, w, prior,
                                                     occlusion_weight, map_sigma_m)
    hyps = distinct_hypotheses(found, cost, yaw, tilt, grid.n_cols, HYPOTHESES)
    if not hyps:
        return (found, cost, yaw), None, ranked
    return (found, cost, yaw), _exact_hypotheses(grid, hyps, lattice, m, w, height_m, occlusion_weight,
                                                 map_sigma_m), ranked


def joint_covariance_cells(render_at: _Renderer, rays: np.ndarray, row: float, col: float, eye_offset_m: float,
                           pose: CameraPose, scale: float, prior: OrientationPrior, sigma_deg: float,
                           weight_per_ray: float) -> np.ndarray | None:
    """The (row, col) covariance (cells^2) of the position with the orientation free: the
    Gauss-Newton curvature of the rays' residuals on renders over (row, col, yaw, pitch, roll, focal
    scale), each ray weighing ``weight_per_ray`` (the skyline's independent share spread over its
    rays), the orientation's tolerances as priors, marginalised onto the position and scaled as the
    estimator scales its own (``confidence.COVARIANCE_SCALE``).  The estimate's covariance holds the
    orientation fixed and is too tight where the position trades against the yaw or the focal length.
    None when the curvature is singular."""
    steps = np.array([0.05, 0.05, 0.01, 0.01, 0.01, 1e-4])
    base = np.array([row, col, pose.yaw_deg, pose.pitch_deg, pose.roll_deg, math.log(scale)])

    def residual(p: np.ndarray) -> np.ndarray:
        return _joint_residual_deg(render_at, rays, p, eye_offset_m)

    e0 = residual(base)
    J = np.empty((e0.size, 6))
    for i in range(6):
        d = np.zeros(6)
        d[i] = steps[i]
        J[:, i] = (residual(base + d) - residual(base - d)) / (2.0 * steps[i])
    ok = np.isfinite(e0) & np.all(np.isfinite(J), axis=1) & (np.abs(e0) < 3.0 * max(sigma_deg, FIT_SCALE_DEG))
    if ok.sum() < 8:
        return None
    H = weight_per_ray * (J[ok].T @ J[ok]) / sigma_deg**2
    info = np.zeros(6)
    info[3] = 1.0 / max(prior.pitch_tolerance_deg / 2.0, 1e-3) ** 2
    info[4] = 1.0 / max(prior.roll_tolerance_deg / 2.0, 1e-3) ** 2
    info[5] = 1.0 / max(prior.focal_sigma, 1e-4) ** 2
    if prior.heading_deg is not None and prior.heading_tolerance_deg < 180.0:
        info[2] = 1.0 / max(prior.heading_tolerance_deg / 2.0, 1e-3) ** 2
    try:
        cov = np.linalg.inv(H + np.diag(info))
    except np.linalg.LinAlgError:
        return None
    out = confidence.COVARIANCE_SCALE * cov[:2, :2]
    return out if np.all(np.isfinite(out)) and out[0, 0] > 0 and out[1, 1] > 0 else None


def _with_joint_covariance(pos: Position, grid: SkylineGrid, render_at: _Renderer, rays: np.ndarray,
                           pose: CameraPose, scale: float, prior: OrientationPrior, eye_offset_m: float) -> Position:
    """The answer with its covariance widened to :func:`joint_covariance_cells`'s where that is wider
    (the orientation free), in east/north metres."""
    res = pos.result
    sigma = float(np.mean(res.sigma_deg))
    independent = res.independent_azimuths if math.isfinite(res.independent_azimuths) else float(res.n_valid)
    cov_cells = joint_covariance_cells(render_at, rays, res.row, res.col, eye_offset_m, pose, scale, prior, sigma,
                                       independent / max(rays.shape[0], 1))
    if cov_cells is None:
        return pos
    node = min(max(int(round(res.row)), 0), grid.n_rows - 1) * grid.n_cols + min(max(int(round(res.col)), 0),
                                                                                 grid.n_cols - 1)
    joint = confidence.grid_to_east_north(cov_cells, grid.dx_m, grid.dy_m, float(grid.convergence_deg[node]))
    current = res.covariance_m2
    if current is not None and np.linalg.det(joint) <= np.linalg.det(current):
        return pos
    return replace(pos, estimate=replace(res, covariance_m2=joint))


def _at_tolerance(pose: CameraPose, scale: float, prior: OrientationPrior) -> str:
    """What of the orientation lies at its bound (pitch, roll, focal length), '' when nothing does."""
    if abs(pose.pitch_deg) >= prior.pitch_tolerance_deg + BOUND_MARGIN_DEG - AT_BOUND_DEG:
        return "pitch"
    if abs(pose.roll_deg) >= prior.roll_tolerance_deg + BOUND_MARGIN_DEG - AT_BOUND_DEG:
        return "roll"
    if prior.focal_sigma > 0.0 and abs(math.log(scale)) >= BOUND_SIGMAS * prior.focal_sigma * (1.0 - AT_BOUND_SHARE):
        return "focal length"
    return ""


def _same_place_cells(pos: Position, grid: SkylineGrid) -> float:
    """How far (cells) from the answer a node still stands for the same place: SAME_PLACE_CELLS, or
    twice the answer's 95 % radius where that is wider."""
    cov = pos.result.covariance_m2
    if cov is None or not np.all(np.isfinite(cov)):
        return SAME_PLACE_CELLS
    return max(SAME_PLACE_CELLS, 2.0 * confidence.radius_m(cov) / math.sqrt(grid.dx_m * grid.dy_m))


def _screened_better(grid: SkylineGrid, pos: Position, screened: Screened, same_place_cells: float,
                     weighed: Sequence[Hypothesis]) -> int:
    """How many of the screening's best nodes (the ones moved within their cells) lie farther than
    ``same_place_cells`` from the answer, scored at or below the best of those near it (all of them
    when none near it made the list), and are not the same answer as one of the ``weighed`` hypotheses
    (:func:`appliance.estimator.orientation.same_hypothesis`: those were weighed with their own
    orientation, :func:`refit_rivals`).  The screening is the only look the others get: where it
    ranks them above the answer's place, the fits of a few hypotheses cannot rule them out."""
    nodes, cost, yaw = screened
    res = pos.result
    rows, cols = np.divmod(nodes, grid.n_cols)
    d = np.hypot(rows - res.row, cols - res.col)
    near = d <= max(1.5, 0.5 * same_place_cells)
    far = d > same_place_cells
    if near.any():
        far &= cost <= float(cost[near].min())
    return sum(not any(same_hypothesis(float(rows[i]), float(cols[i]), float(yaw[i]), h, grid.n_cols)
                       for h in weighed) for i in np.flatnonzero(far))


def _rivals(pos: Position, fitted: list[tuple[Hypothesis, Fit]], grid: SkylineGrid, same_place_cells: float) -> int:
    """How many hypotheses away from the answer (beyond ``same_place_cells``) fit within RIVAL_NATS of the best
    one, the costs weighed at the noise the estimate learned and the skyline's independent share."""
    res = pos.result
    sigma = max(float(np.mean(res.sigma_deg)), 1e-3)
    best = min(f.ssd / f.n for _, f in fitted)
    share = res.independent_azimuths / max(res.n_valid, 1) if math.isfinite(res.independent_azimuths) else 1.0
    count = 0
    for _, f in fitted:
        if math.hypot(f.row - res.row, f.col - res.col) <= same_place_cells:
            continue
        nats = (f.ssd / f.n - best) * res.n_valid / (2.0 * sigma**2) * min(share, 1.0)
        if nats < RIVAL_NATS:
            count += 1
    return count


def profiled_cauchy_nats(residual_deg: np.ndarray, open_sky: np.ndarray | None = None) -> float:
    """The mean log-likelihood per ray (nats) of residuals (deg; NaN where no terrain, counted as
    NO_TERRAIN_RESIDUAL_DEG) under a Cauchy density, its scale at its most likely within
    PROFILE_SCALE_DEG.  Cauchy is the orientation fits' own loss: a near object or a cloud taken for
    terrain costs the log of its residual, not its square, so it weighs alike at every place.  Where
    ``open_sky`` (the map ends close under the rendered horizon), a ray above the render costs at most
    log OPEN_SPAN_DEG: unseen terrain beyond the edge may hold it."""
    r = np.nan_to_num(np.asarray(residual_deg, dtype=np.float64), nan=NO_TERRAIN_RESIDUAL_DEG)
    e = np.minimum(np.abs(r), NO_TERRAIN_RESIDUAL_DEG)
    if e.size == 0:
        return -math.inf
    above_open = None if open_sky is None else np.asarray(open_sky, dtype=bool) & (r > 0.0)

    def minus_mean_ll(log_s: float) -> float:
        s = math.exp(log_s)
        cost = np.log(math.pi * s * (1.0 + (e / s) ** 2))
        if above_open is not None:
            cost = np.where(above_open, np.minimum(cost, math.log(OPEN_SPAN_DEG)), cost)
        return float(np.mean(cost))

    from scipy.optimize import minimize_scalar  # here, not at import: see start_loading_optimizer

    lo, hi = (math.log(v) for v in PROFILE_SCALE_DEG)
    best = minimize_scalar(minus_mean_ll, bounds=(lo, hi), method="bounded", options={"xatol": 1e-4})
    return -min(float(best.fun), minus_mean_ll(lo), minus_mean_ll(hi))


def _nats_at(render_at: _Renderer, rays: np.ndarray, row: float, col: float, pose: CameraPose, scale: float,
             eye_offset_m: float) -> float:
    """:func:`profiled_cauchy_nats` of the photo's rays seen with ``pose`` and focal ``scale`` against the
    render at (``row``, ``col``)."""
    az, el = directions(rays, pose, scale)
    rendered, open_sky = render_at.seen(row, col, np.mod(az, 360.0), eye_offset_m)
    return profiled_cauchy_nats(el - rendered, open_sky)


def _solved_nats(render_at: _Renderer, rays: np.ndarray, row: float, col: float, pose: CameraPose, scale: float,
                 eye_offset_m: float, prior: OrientationPrior) -> tuple[OrientationFit, float]:
    """The orientation solved at (``row``, ``col``) from ``pose`` and ``scale`` on its render, and the
    rays' :func:`profiled_cauchy_nats` with it."""
    az_grid, el_grid, open_sky = _rendered_view(render_at, row, col, rays, pose, scale, eye_offset_m)
    o = solve_orientation(rays, az_grid, el_grid, pose, prior, scale, open_sky)
    return o, _nats_at(render_at, rays, row, col, o.pose, o.focal_scale, eye_offset_m)


def _refit(render_at: _Renderer, rays: np.ndarray, hf: tuple[Hypothesis, Fit], prior: OrientationPrior,
           level: CameraPose) -> tuple[OrientationFit, float]:
    """A hypothesis' orientation solved on its own render from its exact fit's (the EXIF focal length),
    and its nats there."""
    h, f = hf
    return _solved_nats(render_at, rays, f.row, f.col, _pose_of_fit(h, f, level), 1.0, f.eye_offset_m, prior)


def _finite_or_lowest(nats: float) -> float:
    return nats if math.isfinite(nats) else -math.inf


def _confined(grid: SkylineGrid, log_prior: np.ndarray | None, row: float, col: float, cells: float) -> np.ndarray:
    """``log_prior`` (0 everywhere when None) with -inf at the nodes farther than ``cells`` from (``row``, ``col``)."""
    rows, cols = np.divmod(np.arange(grid.offset_deg.size), grid.n_cols)
    near = np.hypot(rows - row, cols - col) <= cells
    return np.where(near, 0.0 if log_prior is None else log_prior, -np.inf)


@dataclass(frozen=True)
class RefitRivals:
    """What the hypotheses refitted with their own orientation say of the answer: how many lie
    beyond the same place and fit within RIVAL_NATS of it (``rivals``), the odds of all those beyond
    the same place together against the answer (``odds_elsewhere``: the sum of their likelihood
    ratios, each exp(-nats)), how many lie inside it but more than SAME_PLACE_CELLS away and fit
    better than it by more than RIVAL_NATS (``better``), and each hypothesis' nats below the answer
    (negative: it fits better; NaN at the same place).  A hypothesis within JOINT_REACH_CELLS of the
    same place whose joint fit of position and orientation comes back to the answer (SAME_PLACE_CELLS)
    is none of these: it lies on the answer's own slope."""

    rivals: int
    better: int
    nats: tuple[float, ...]
    odds_elsewhere: float = 0.0

    @property
    def crowded(self) -> bool:
        """Whether the places beyond the same place together hold more than the rival level: the answer,
        the best of the hypotheses, is picked from them, so a margin over each one is not a margin over all."""
        return self.odds_elsewhere > math.exp(-RIVAL_NATS)


def refit_rivals(render_at: _Renderer, rays: np.ndarray, fitted: list[tuple[Hypothesis, Fit]], pos: Position,
                 grid: SkylineGrid, pose: CameraPose, scale: float, eye_offset_m: float, prior: OrientationPrior,
                 same_place_cells: float, level: CameraPose = LEVEL,
                 refits: Sequence[tuple[OrientationFit, float]] | None = None,
                 passed: Sequence[tuple[float, float, float]] = ()) -> RefitRivals:
    """Each hypothesis farther than SAME_PLACE_CELLS from the answer, its yaw, pitch, roll and focal
    length solved on its own render as the answer's were (:func:`solve_orientation`), weighed
    against the answer (``pose``, ``scale`` at the estimate's place, or its orientation solved there
    again where that fits better) by :func:`profiled_cauchy_nats`
    over ``rays``, the rays counting together for the skyline's independent azimuths less the
    PHOTO_FITTED_PARAMETERS each place's fit takes from them (at least one): a photo's few azimuths
    tell places apart only by what its orientation and lens cannot absorb.  ``level``: the pitch and roll
    the hypotheses' screening levelled the rays through (:func:`_pose_of_fit`).  ``refits``: the
    hypotheses' refits (:func:`_refit`, in the order of ``fitted``) when they were made already.
    ``passed``: other places (row, col, nats) weighed already, the estimate's that it was taken back
    from (they count as the hypotheses do, after them in ``nats``)."""
    res = pos.result
    independent = res.independent_azimuths if math.isfinite(res.independent_azimuths) else float(res.n_valid)
    independent = max(independent - PHOTO_FITTED_PARAMETERS, 1.0)
    # the answer weighed as the hypotheses are: its orientation solved again on its own render (its pose
    # came from the joint fit, made before the estimate placed it where it stands), the better of the two
    answer = max(_nats_at(render_at, rays, res.row, res.col, pose, scale, eye_offset_m),
                 _solved_nats(render_at, rays, res.row, res.col, pose, scale, eye_offset_m, prior)[1])
    dist = [math.hypot(f.row - res.row, f.col - res.col) for _, f in fitted]
    if refits is None:
        # each hypothesis' refit on its own: on the kernels' threads (mostly ray marches, which release the GIL)
        away = iter(start_on_threads(lambda hf: _refit(render_at, rays, hf, prior, level),
                                     [hf for hf, d in zip(fitted, dist) if d > SAME_PLACE_CELLS])())
        refits = [next(away) if d > SAME_PLACE_CELLS else (None, math.nan) for d in dist]  # type: ignore[misc]
    rivals = better = 0
    elsewhere: list[float] = []  # the nats behind the answer of the places beyond the same place
    nats: list[float] = []
    for (_, f), d, (o, own) in zip(fitted, dist, refits):
        if d <= SAME_PLACE_CELLS:
            nats.append(math.nan)
            continue
        n = independent * (answer - own)
        nats.append(n)
        beyond = d > same_place_cells and n < ODDS_NATS
        fits_better = d <= same_place_cells and n < -RIVAL_NATS
        if (beyond or fits_better) and d <= same_place_cells + JOINT_REACH_CELLS:
            # within reach of the answer: a rival only if the joint fit of position and orientation
            # from it does not come back to the answer (another optimum, not the answer's slope)
            row, col, _, _ = fit_jointly(render_at, rays, f.row, f.col, f.eye_offset_m, o.pose, o.focal_scale,
                                         prior)
            if math.hypot(row - res.row, col - res.col) <= SAME_PLACE_CELLS:
                beyond = fits_better = False
        if beyond:
            elsewhere.append(n)
        rivals += int(beyond and n < RIVAL_NATS)
        better += int(fits_better)
    for row, col, own in passed:
        d = math.hypot(row - res.row, col - res.col)
        if d <= SAME_PLACE_CELLS:
            continue
        n = independent * (answer - own)
        nats.append(n)
        if d > same_place_cells:
            elsewhere.append(n)
        rivals += int(d > same_place_cells and n < RIVAL_NATS)
        better += int(d <= same_place_cells and n < -RIVAL_NATS)
    return RefitRivals(rivals, better, tuple(nats), odds_against(elsewhere))


def odds_against(nats_behind: Sequence[float]) -> float:
    """The odds of a set of places together against the answer: the sum of their likelihood ratios
    exp(-nats), each place ``nats_behind`` the answer (those more than ODDS_NATS behind left out)."""
    return float(sum(math.exp(-n) for n in nats_behind if n < ODDS_NATS))
