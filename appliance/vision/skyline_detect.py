"""Skyline detection in a panorama: pixels -> per-azimuth skyline elevation (degrees).

Two methods:

- ``gradient`` (the Viper paper's): per column, the image is smoothed vertically with a Gaussian
  and the first pixel from the top whose downward intensity drop exceeds a threshold is the skyline.
  Fast and exact on a clean sky, but a cloud's lower edge or a person stops it.
- ``dp`` (the default): dynamic programming across columns (after Lie et al. 2005).  Every pixel
  gets a cost from the downward drop of intensity (an edge) and from how sky-like the pixels just
  above it and how ground-like those just below it are; the path minimises the summed cost plus a
  penalty per row of vertical jump between neighbouring columns.  The sky/ground colour models are
  learnt from the image itself (a first pass with generic priors, then a second pass with Gaussian
  models fitted on both sides of the first path), so clouds, glare and haze do not break the line.

Per-column confidence: where the pixels above the line do not look like sky, the pixels below do not
look like ground, or the edge is too weak (a person, a pole, a panorama without sky), the column is
missing (NaN), never guessed.  The learnt colour models are checked against a generic prior (sky is
smooth and bright): a column must show such sky somewhere above its line, so an image without sky
yields nothing, while a cloud sitting on a ridge, textured itself, does not drop the column when
clear sky shows above it.  A ridge with white cumulus behind it (the pixels just above its line bright,
white and over dark ground, :func:`appliance.vision.skyline_edges.cloud_above`) is judged with the
cloud as sky where it continues the line found under clear sky on both sides.  Far ground under haze
(a plain seen from a summit) may look as much like the learnt sky as the sky itself; it is darker and
bluer than the whitened sky just above the horizon, and darker again further down, which the second
path through the unconfident columns takes for ground (:func:`_bridge`).  A run of a few unconfident
columns in a continuous line, on a strong edge onto ground, is joined to the line (:func:`_join_gaps`).
Masked azimuth ranges are missing too.

The per-pixel work (features, colour models, costs and the path) is in
:mod:`appliance.vision.skyline_pixels`.  Fresh snow brighter than its sky (the brightness drop is
then at the rocks below the skyline) is handled by a second path on the sky/snow colour boundary
(:mod:`appliance.vision.skyline_snow`).  There, a panorama stitched from the capture ring's frames
also says which pixels moved between overlapping frames (:attr:`Panorama.motion`,
:mod:`appliance.vision.temporal`): a drifting cloud is sky even where it is as white as the snow.
Motion is evidence of sky only; a panorama without it (a file, one photo) is detected as before.

Elevations come from the panorama's geometry (:class:`Panorama`), with sub-pixel refinement of
the edge position.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from appliance.errors import ConfigError, InputError
from appliance.skyline import Skyline
from appliance.vision.panorama import Panorama
from appliance.vision.skyline_edges import (
    VOID_MARGIN_PX,
    anchored,
    blue_minus_red,
    cloud_above,
    colour_edge,
    fill_void,
    haze_edge,
    haze_reversal,
    hazy_ground,
    horizontal_luma,
    near_rows,
    sharpness_confidence,
)
from appliance.vision.skyline_pixels import (
    _best_mean_above_t,
    _cost_columns,
    _downward_drop,
    _dp_path,
    _features,
    _gaussian_llr,
    _luma,
    _sky_prior,
    _texture,
    _to_float,
    intensity,
    line_band,
)
from appliance.vision.skyline_snow import SnowEvidence, colour_rows, snow_checks, snow_evidence
from appliance.vision.temporal import cloud_below, motion_edge, moving_around, moving_pixels


class Method(enum.Enum):
    DP = "dp"
    GRADIENT = "gradient"


@dataclass(frozen=True)
class DetectionConfig:
    """Tunables of skyline detection (units in the names; intensities on a 0..1 scale)."""

    method: Method = Method.DP
    smooth_sigma_px: float = 1.5  # vertical Gaussian smoothing before the gradient
    gradient_threshold: float = 0.06  # gradient method: minimum downward drop (0..1 intensity)
    min_elevation_deg: float = -45.0  # rows outside this elevation window are not searched
    max_elevation_deg: float = 60.0
    max_jump_px: int = 3  # dp: largest vertical step between neighbouring columns
    max_steep_run_px: int = 4  # dp: a path climbing at max_jump_px longer than this is an occluder
    jump_cost: float = 0.08  # dp: cost per row of vertical step
    band_px: int = 12  # dp: rows above/below a candidate whose sky/ground likeness is scored
    edge_weight: float = 3.0  # dp: weight of the edge term against the region term
    min_edge: float = 0.02  # confidence: weakest acceptable downward drop (0..1 intensity)
    min_confidence: float = 0.5  # columns below this confidence are missing
    chroma_weight: float = 0.7  # dp: weight of the blue-minus-red drop beside the intensity drop (0: off)
    edge_far_px: int = 6  # sharpness: the fall per row above the line is measured from 3 to this many rows up
    max_slope_ratio: float = 0.3  # sharpness: fall per row above the line over that across it, at zero confidence
    cloud: bool = True  # dp: white cloud just above a line over dark ground counts as sky (skyline_edges.cloud_above)
    snow: bool = True  # dp: on snowy ground, find the sky/snow boundary by colour (appliance.vision.skyline_snow)
    motion: bool = True  # dp, over snow: pixels that moved between the ring's frames are sky (vision.temporal)
    cloud_colour: bool = True  # dp, over snow: white less blue than the snow is cloud (skyline_snow.white_cloud)
    step_deg: float = 1.0  # azimuth sampling of the output skyline

    def __post_init__(self) -> None:
        if not isinstance(self.method, Method):
            object.__setattr__(self, "method", Method(self.method))
        if self.smooth_sigma_px <= 0:
            raise ConfigError(f"skyline.smooth_sigma_px must be positive, got {self.smooth_sigma_px}")
        if self.max_jump_px < 1:
            raise ConfigError(f"skyline.max_jump_px must be at least 1, got {self.max_jump_px}")
        if not 0 < self.step_deg <= 10:
            raise ConfigError(f"skyline.step_deg must be in (0, 10], got {self.step_deg}")
        if self.min_elevation_deg >= self.max_elevation_deg:
            raise ConfigError(
                f"skyline: min_elevation_deg {self.min_elevation_deg} >= max_elevation_deg {self.max_elevation_deg}"
            )


@dataclass(frozen=True)
class ColumnSkyline:
    """The skyline per panorama column: fractional row, elevation (deg, NaN = missing), confidence."""

    azimuth_deg: np.ndarray
    row: np.ndarray
    elevation_deg: np.ndarray
    confidence: np.ndarray


# ----------------------------------------------------------------------------- azimuth masks


def parse_mask(text: str) -> list[tuple[float, float]]:
    """Parse ``"10-30,350-5"`` (degrees, clockwise from north; a range may wrap through north)."""
    ranges: list[tuple[float, float]] = []
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        lo, sep, hi = part.partition(":") if ":" in part else _split_range(part)
        try:
            a, b = float(lo), float(hi)
        except ValueError:
            raise InputError(f"mask range {part!r}: expected START-END in degrees, e.g. 120-135") from None
        if not sep or not (math.isfinite(a) and math.isfinite(b)):
            raise InputError(f"mask range {part!r}: expected START-END in degrees, e.g. 120-135")
        ranges.append((a % 360.0, b % 360.0))
    return ranges


def _split_range(part: str) -> tuple[str, str, str]:
    # a leading minus belongs to the first number: "-10-20" is -10..20
    idx = part.find("-", 1)
    if idx < 0:
        return part, "", ""
    return part[:idx], "-", part[idx + 1 :]


def in_mask(azimuth_deg: np.ndarray, ranges: list[tuple[float, float]]) -> np.ndarray:
    """True where an azimuth lies within one of the (start, end) ranges (clockwise from start)."""
    az = np.mod(np.asarray(azimuth_deg, dtype=np.float64), 360.0)
    out = np.zeros(az.shape, dtype=bool)
    for a, b in ranges:
        width = (b - a) % 360.0
        out |= np.mod(az - a, 360.0) <= width
    return out


# ----------------------------------------------------------------------------- dynamic programming


def _path_cost(
    edge: np.ndarray, llr: np.ndarray, cfg: DetectionConfig, masked: np.ndarray, edge_weight: float
) -> np.ndarray:
    """The DP cost, transposed (WxH float32), of every pixel of an HxW edge and sky log-likelihood map."""
    llr_t = cv2.transpose(np.ascontiguousarray(llr, dtype=np.float32))
    edge_t = cv2.transpose(np.ascontiguousarray(edge, dtype=np.float32))
    return np.asarray(_cost_columns(llr_t, edge_t, np.ascontiguousarray(masked), cfg.band_px, float(edge_weight)))


def _run_dp(cost_t: np.ndarray, cfg: DetectionConfig, wrap: bool) -> np.ndarray:
    w = cost_t.shape[0]
    if not wrap:
        return np.asarray(_dp_path(cost_t, cfg.max_jump_px, cfg.jump_cost))
    # a full circle: run over a copy extended on both sides so that no seam sits at column 0
    pad = min(w, 200)
    ext = np.concatenate([cost_t[-pad:], cost_t, cost_t[:pad]], axis=0)
    return np.asarray(_dp_path(ext, cfg.max_jump_px, cfg.jump_cost))[pad : pad + w]


# ----------------------------------------------------------------------------- detection


def _search_rows(pano: Panorama, cfg: DetectionConfig) -> tuple[int, int]:
    r_top = float(pano.elevation_to_row(min(cfg.max_elevation_deg, 89.0)))
    r_bot = float(pano.elevation_to_row(max(cfg.min_elevation_deg, -89.0)))
    top = max(0, int(math.floor(r_top)))
    bot = min(pano.height, int(math.ceil(r_bot)) + 1)
    if bot - top < 8:
        raise InputError(
            f"panorama: the elevation window {cfg.min_elevation_deg}..{cfg.max_elevation_deg} deg"
            f" covers only {max(bot - top, 0)} rows of {pano.height}"
        )
    return top, bot


def _refine(drop: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Sub-pixel edge position: the drop's local maximum near each row, by a parabola fit."""
    h, w = drop.shape
    cols = np.arange(w)
    r = np.clip(rows, 1, h - 2).astype(np.int64)
    # move to the strongest drop within +-2 rows
    cand = np.stack([np.clip(r + k, 1, h - 2) for k in (-2, -1, 0, 1, 2)])
    vals = drop[cand, cols[None, :]]
    r = cand[np.argmax(vals, axis=0), cols]
    y0, y1, y2 = drop[r - 1, cols], drop[r, cols], drop[r + 1, cols]
    den = y0 - 2 * y1 + y2
    off = np.where(den < -1e-9, 0.5 * (y0 - y2) / np.where(den < -1e-9, den, -1.0), 0.0)
    return r + np.clip(off, -0.5, 0.5)


def detect_columns(
    pano: Panorama, cfg: DetectionConfig | None = None, mask: list[tuple[float, float]] | None = None
) -> ColumnSkyline:
    """The skyline in every column of the panorama (row, elevation, confidence); NaN = missing, as
    in the columns of ``mask`` and the panorama's empty ones."""
    cfg = cfg or DetectionConfig()
    top, bot = _search_rows(pano, cfg)
    cols = np.arange(pano.width, dtype=np.float64)
    az = pano.column_azimuth_deg(cols)
    masked = in_mask(az, mask or [])
    if pano.empty_columns is not None:
        masked = masked | pano.empty_columns
    image, void = fill_void(np.ascontiguousarray(pano.image[top:bot]))
    motion = None if pano.motion is None else np.ascontiguousarray(pano.motion[top:bot])
    rows_local, conf = detect_rows(image, cfg, masked, wrap=pano.full_circle, motion=motion)
    # a line at the border of the area no photo reached (the padding) is that border's edge
    near_void = near_rows(void, rows_local, VOID_MARGIN_PX)
    rows_local = np.where(near_void, np.nan, rows_local)
    conf = np.where(near_void, 0.0, conf)
    valid = np.isfinite(rows_local)
    rows = np.where(valid, rows_local + top, np.nan)
    el = np.where(valid, pano.row_elevation_deg(np.where(valid, rows, 0.0)), np.nan)
    return ColumnSkyline(az, rows, el, conf)


def detect_rows(
    img8: np.ndarray, cfg: DetectionConfig, masked: np.ndarray | None = None, wrap: bool = False,
    motion: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The skyline's fractional row in every column of an HxWx3 uint8 image, and its confidence.

    Rows are NaN where the confidence is below ``cfg.min_confidence`` or the column is ``masked``
    (a boolean per column); ``wrap`` joins the last column to the first (a full circle).  ``motion``
    (HxW, :attr:`appliance.vision.panorama.Panorama.motion`) marks the pixels that moved between
    the capture ring's frames: sky (used over snow, :func:`_snow_rows`).
    """
    masked = np.zeros(img8.shape[1], dtype=bool) if masked is None else np.asarray(masked, dtype=bool)
    lum = cv2.GaussianBlur(intensity(img8), (0, 0), sigmaX=0.7, sigmaY=cfg.smooth_sigma_px)
    drop = _downward_drop(lum)
    if cfg.method is Method.GRADIENT:
        rows, conf = _gradient_rows(drop, cfg)
    else:
        rows, conf = _dp_rows(img8, lum, drop, cfg, masked, wrap=wrap, motion=motion)
    valid = np.isfinite(rows) & (conf >= cfg.min_confidence) & ~masked
    return np.where(valid, rows, np.nan), np.where(masked, 0.0, conf)


def _gradient_rows(drop: np.ndarray, cfg: DetectionConfig) -> tuple[np.ndarray, np.ndarray]:
    above = drop > cfg.gradient_threshold
    found = above.any(axis=0)
    first = np.argmax(above, axis=0)
    rows = _refine(drop, first)
    return np.asarray(np.where(found, rows, np.nan)), np.asarray(found, dtype=np.float64)


def _dp_rows(
    img8: np.ndarray, lum: np.ndarray, drop: np.ndarray, cfg: DetectionConfig, masked: np.ndarray, wrap: bool,
    motion: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    h, w = drop.shape
    # the region terms are computed at half resolution: they are band averages anyway
    hs, ws = max(2, h // 2), max(2, w // 2)
    small = _to_float(cv2.resize(img8, (ws, hs), interpolation=cv2.INTER_AREA))
    small_sm = cv2.GaussianBlur(small, (0, 0), sigmaX=0.5, sigmaY=max(0.5, cfg.smooth_sigma_px / 2))
    drop_small = _downward_drop(_luma(small_sm)) * np.float32(2.0)
    texture = _texture(_luma(small))
    prior = _sky_prior(small_sm, texture)
    mask_small = cv2.resize(masked.astype(np.uint8)[None, :], (ws, 1), interpolation=cv2.INTER_NEAREST)[0] > 0
    # the first pass trusts the regions more than the edges: near ridges have the strongest edges
    path_small = _run_dp(_path_cost(drop_small, prior, cfg, mask_small, cfg.edge_weight * 0.5), cfg, wrap)
    # learn sky and ground colours on both sides of the first path, then run again at full size
    llr_small = _learn_llr(small_sm, texture, path_small, cfg, mask_small)
    llr_small = prior if llr_small is None else 0.5 * llr_small + 0.5 * prior
    llr = cv2.resize(llr_small, (w, h), interpolation=cv2.INTER_LINEAR)
    path = _run_dp(_path_cost(drop, llr, cfg, masked, cfg.edge_weight), cfg, wrap)
    rows = _refine(drop, path)
    # the generic prior vetoes a "sky" that is textured (an image without sky) unless the column has
    # clear sky somewhere above the line: a cloud sitting on the ridge is textured, but above it or
    # through a gap the column shows the sky the learnt model was taught on
    # (bilinear upsampling and transposition commute: the full-size prior is made transposed, WxH)
    prior_full_t = cv2.resize(cv2.transpose(prior), (h, w), interpolation=cv2.INTER_LINEAR)
    lum_h = horizontal_luma(img8)
    chroma = blue_minus_red(img8, cfg.smooth_sigma_px)
    edge = colour_edge(drop, chroma, cfg.chroma_weight)
    # (texture is a 5x5 box at half size: it bleeds about ten rows across the edge)
    sky_somewhere = _best_mean_above_t(prior_full_t, np.ascontiguousarray(path, dtype=np.int64), 10, 8)
    sharp = sharpness_confidence(lum_h, rows, cfg.edge_far_px, cfg.min_edge, cfg.max_slope_ratio)
    cap = np.minimum(np.clip((sky_somewhere + 1.0) / 0.3, 0.0, 1.0), sharp)
    conf = np.minimum(_confidence(edge, llr, path, cfg, prior_full_t), cap)
    cloud = cloud_above(img8, rows) if cfg.cloud else np.zeros(w, dtype=bool)
    if cfg.cloud:
        conf = _cloud_columns(cloud, edge, llr, path, rows, conf, sharp, cfg, prior_full_t, wrap)
    # a line whose pixels just above are less like the learnt sky than like the ground (passed on the
    # leniency for pale sky at the skyline) neither anchors the second path nor is kept from it
    # (white cloud just above explains it: the cloud's top is no better a skyline)
    doubtful = (conf >= cfg.min_confidence) & (_sky_above(llr, path) < DOUBTFUL_SKY) & ~cloud
    bridged = _bridge(drop, llr, path, np.where(doubtful, 0.0, conf), cfg, masked, wrap, prior_full_t, edge,
                      lum, chroma)
    if bridged is not None:
        path2, conf2, line = bridged
        rows2 = _refine(drop, path2)
        conf2 = np.minimum(conf2, sharpness_confidence(lum_h, rows2, cfg.edge_far_px, cfg.min_edge,
                                                       cfg.max_slope_ratio))
        if cfg.cloud:
            # the second path is for faint edges under clear sky: a faint edge under white cloud is the
            # cloud's base
            conf2 = np.where(cloud_above(img8, rows2), 0.0, conf2)
        take = ((conf < cfg.min_confidence) | doubtful) & (conf2 >= cfg.min_confidence)
        rows = np.where(take, rows2, rows)
        # a doubtful line the second path did not replace, well below the line joining the confident
        # columns (a near hill's top under far land seen through haze), is left out
        dip = doubtful & ~take & (rows > line + DOUBTFUL_DIP_BANDS * cfg.band_px)
        conf = np.where(take, conf2, np.where(dip, 0.0, conf))
    conf = _join_gaps(rows, conf, edge, llr, cfg, masked, wrap)
    if cfg.snow:
        moving = None if motion is None or not cfg.motion else moving_pixels(motion)
        snowy = _snow_rows(img8, drop, rows, conf, cfg, masked, wrap, prior_full_t, moving)
        if snowy is not None:
            rows, conf = snowy
    return rows, conf


#: A stretch of columns whose line has white cloud above it must meet lines under clear sky on both
#: sides within this many columns, at most CLOUD_ANCHOR_STEP_PX rows from their rows.
CLOUD_ANCHOR_GAP_PX = 16
CLOUD_ANCHOR_STEP_PX = 8.0


def _cloud_columns(
    cloud: np.ndarray,
    edge: np.ndarray,
    llr: np.ndarray,
    path: np.ndarray,
    rows: np.ndarray,
    conf: np.ndarray,
    sharp: np.ndarray,
    cfg: DetectionConfig,
    prior_t: np.ndarray,
    wrap: bool,
) -> np.ndarray:
    """The confidence with the columns whose line has white cloud just above it instead of the
    learnt clear sky (``cloud``: :func:`appliance.vision.skyline_edges.cloud_above`) judged with that
    cloud as sky, capped by the edge's sharpness (``sharp``), where they continue the line found
    under clear sky on both sides (:func:`appliance.vision.skyline_edges.anchored`).  Clear sky
    somewhere above the line is not asked of them (the cloud may fill the column to the image's
    top): the lines on both sides, which had to show it, stand for it."""
    with_cloud = np.minimum(_confidence(edge, llr, path, cfg, prior_t, cloud=cloud), sharp)
    good = conf >= cfg.min_confidence
    extra = cloud & ~good & (with_cloud >= cfg.min_confidence)
    keep = anchored(extra, good, cloud, rows, CLOUD_ANCHOR_GAP_PX, CLOUD_ANCHOR_STEP_PX, wrap)
    return np.where(keep, with_cloud, conf)


def _snow_rows(
    img8: np.ndarray,
    drop: np.ndarray,
    rows: np.ndarray,
    conf: np.ndarray,
    cfg: DetectionConfig,
    masked: np.ndarray,
    wrap: bool,
    prior_t: np.ndarray,
    moving: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """On snowy ground (:mod:`appliance.vision.skyline_snow`), the path run again with the sky/snow
    boundary's score beside the intensity drop as its edge and the sky and snow models learnt at the
    trusted boundary as its regions; its rows and confidence.  None where the ground is not snowy.

    Snow under a pale sky is brighter than the sky: the drop the first path follows is at the top of
    the first dark rock below the skyline.  The rows are placed where the colour crosses halfway from
    the sky's to the ground's within three rows of the path (the brightness of snow under a pale sky
    departs from the sky's a few rows off the boundary, or not at all), and judged there, with the
    colour step onto the snow as an edge beside the brightness drop and the boundary's score; a line
    with snow-coloured pixels just above it is left out.  The
    path takes a brightness drop as an edge only under sky-coloured pixels (the top of a rock in the
    snow has snow above it), and the snow's colour below the line vouches for the ground where the
    learnt models take shaded snow for sky (:func:`_snow_coloured_below`).

    With ``moving`` (HxW boolean, :func:`appliance.vision.temporal.moving_pixels`: what drifted
    between the capture ring's frames), those pixels count as sky in the path's regions and its
    confidence: a white cloud behind a snowy ridge has nearly the snow's colour and brightness,
    but it moves.  White pixels less blue than the snow (with ``cfg.cloud_colour``,
    :func:`appliance.vision.skyline_snow.white_cloud`) join them and are taken as they are: outside
    the frames' overlaps, and in a photo without a motion map, nothing else tells that cloud from
    the snow.  The bottom of the moving pixels over still ones is an edge too, whatever the
    cloud's base's brightness against the snow (:func:`appliance.vision.temporal.motion_edge`), and
    an edge with moving pixels below it is no edge of the path's (the top of a drifting cloud, which
    has the sky's colour step onto white above it, :func:`appliance.vision.temporal.cloud_below`).
    A line with moving pixels below it lies on a cloud, not the ground, and is left out; one with
    moving pixels just above it and none below is judged with those pixels as sky and not by the
    colour above it (the snow below must still look like the learnt snow, and the edge be there).
    """
    ev = snow_evidence(img8, rows, np.isfinite(rows) & (conf >= cfg.min_confidence), wrap)
    if ev is None:
        return None
    if cfg.cloud_colour and ev.cloud is not None:
        # white cloud less blue than the snow is sky as a drifting cloud is, in or out of the frames' overlaps
        moving = ev.cloud if moving is None else moving | ev.cloud
    # a brightness drop onto a rock below the skyline has snow above it, not sky: only a drop under
    # sky-coloured pixels is an edge here
    edge = np.maximum(drop * _sky_coloured_above(ev), np.float32(SNOW_EDGE_SCALE) * ev.score)
    if moving is not None:
        ev = replace(ev, llr=np.where(moving, np.float32(MOVING_LLR), ev.llr).astype(np.float32))
        # under a white cloud there is no colour step onto the snow, and its base may be as bright as the
        # snow: the bottom of the moving pixels over still ones is an edge of its own
        edge = np.maximum(edge, np.float32(SNOW_EDGE_SCALE) * motion_edge(moving))
        # and a boundary onto moving pixels is the top of a drifting cloud: no edge of the ground's
        edge = np.where(cloud_below(moving), np.float32(0.0), edge).astype(np.float32)
    path = _run_dp(_path_cost(edge, ev.llr, cfg, masked, cfg.edge_weight), cfg, wrap)
    placed = colour_rows(ev.chroma, path.astype(np.float64))
    # the boundary's score peaks at the brightness rise, the colour step a row either side of the crossing
    step = np.maximum(edge, np.float32(SNOW_EDGE_SCALE) * ev.colour_step)
    near_edge = cv2.dilate(step, np.ones((3, 1), np.uint8))
    at = np.round(np.where(np.isfinite(placed), placed, path)).astype(np.int64)
    conf = _confidence(near_edge, ev.llr, at, cfg, prior_t, haze_below=True, ground=_snow_coloured_below(ev, at))
    if moving is None:
        return placed, snow_checks(ev, placed, conf, cfg.min_confidence, wrap)
    above, below = moving_around(moving, placed)
    # a drifting cloud just above the line and none below it: the pixels above are sky whatever
    # their colour (the ground below must still look like the learnt snow)
    vouched = above & ~below
    conf = np.where(vouched, np.maximum(conf, _confidence(near_edge, ev.llr, at, cfg, prior_t, cloud=vouched)), conf)
    return placed, snow_checks(ev, placed, conf, cfg.min_confidence, wrap, above, below)


def _snow_coloured_below(ev: SnowEvidence, rows: np.ndarray) -> np.ndarray:
    """Per column in [0, 1]: how much the colour says the line at ``rows`` (integer) is the sky/snow
    boundary: the share of pixels 2-9 rows below it nearer the snow's colour than the sky's (blue
    minus red under the evidence's cut), where the pixels 2-9 rows above it are all nearer the sky's
    (0 otherwise).  Shaded snow near a skyline can be as blue as the learnt sky's brightness and
    texture make it look, but not as blue as the sky's colour."""
    offs = np.arange(2, 10)
    sky = (line_band(ev.chroma, rows, -offs) >= ev.chroma_cut).all(axis=0)
    snow = (line_band(ev.chroma, rows, offs) < ev.chroma_cut).mean(axis=0)
    return np.where(sky, snow, 0.0)


def _sky_coloured_above(ev: SnowEvidence) -> np.ndarray:
    """Per pixel, 1 where the pixels 2-3 rows above it are nearer the sky's colour than the snow's
    (blue minus red above the evidence's cut), else 0 (float32)."""
    above = np.empty_like(ev.chroma)
    above[3:] = 0.5 * (ev.chroma[:-3] + ev.chroma[1:-2])
    above[:3] = ev.chroma[:1]
    return (above >= ev.chroma_cut).astype(np.float32)


#: Moving pixels (:func:`appliance.vision.temporal.moving_pixels`) are this sure to be sky (the
#: region terms clip the log-likelihood ratio to +-1).
MOVING_LLR = 1.0


#: The sky/snow score (0..1) becomes an edge of this intensity drop (the path's edge saturates at 0.1).
SNOW_EDGE_SCALE = 0.1


#: The second path's window reaches this many band_px rows below the line joining the confident
#: columns (2 band_px above it): a faint horizon lies about on that line, a near hill's top below it.
BRIDGE_BELOW_BANDS = 1.0


def _bridge(
    drop: np.ndarray,
    llr: np.ndarray,
    path: np.ndarray,
    conf: np.ndarray,
    cfg: DetectionConfig,
    masked: np.ndarray,
    wrap: bool,
    prior_t: np.ndarray,
    edge: np.ndarray,
    lum: np.ndarray,
    chroma: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A second path through the columns the first one left unconfident, kept within ``2 band_px``
    rows above and ``BRIDGE_BELOW_BANDS band_px`` rows below the line joining the confident columns
    on either side, its confidence and that line.

    A faint edge (a hazy far horizon) loses the first path to a stronger edge lower down, in the
    terrain; behind an occluder the first path may cut through it.  The window keeps the second path
    on the skyline's course, and the second path must pass the same confidence test, so a rock or a
    person filling the window stays missing (no sky above the line) while a faint horizon with sky
    above it and ground below is found.

    Far ground under haze may be as like the learnt sky as the sky is; it is darker and bluer than
    the sky whitened at the horizon above it (:func:`appliance.vision.skyline_edges.haze_reversal`:
    counted as ground in this path's regions; the rise of blue minus red onto it is an edge,
    :func:`appliance.vision.skyline_edges.haze_edge`), and where the pixels below the line are so,
    and darker still further down, they pass for ground in its confidence
    (:func:`appliance.vision.skyline_edges.hazy_ground`); the pixels above must still be the learnt
    sky.  ``lum`` is the detector's smoothed intensity and ``chroma`` its blue minus red.
    """
    h, w = drop.shape
    good = (conf >= cfg.min_confidence) & ~masked
    weak = ~good & ~masked
    if not weak.any() or good.sum() < max(8, w // 50):
        return None
    cols = np.arange(w, dtype=np.float64)
    anchors = cols[good]
    anchor_rows = path[good].astype(np.float64)
    if wrap:
        line = np.interp(cols, anchors, anchor_rows, period=float(w))
    else:
        line = np.interp(cols, anchors, anchor_rows)
    window = 2 * cfg.band_px
    below = BRIDGE_BELOW_BANDS * cfg.band_px
    rr = np.arange(h, dtype=np.float64)[None, :]
    outside = (rr < line[:, None] - window) | (rr > line[:, None] + below)
    # far ground under haze is bluer than the whitened sky at the horizon: that rise is an edge too
    hazy_edge = haze_edge(drop, chroma, cfg.chroma_weight)
    # and it is darker and bluer than the sky above it: ground, however like the learnt sky its colour is
    if cfg.chroma_weight > 0:
        llr_path = llr - np.float32(2.0) * haze_reversal(lum, chroma, cfg.band_px, 2 * cfg.band_px)
    else:
        llr_path = llr
    cost_t = _path_cost(hazy_edge, llr_path, cfg, masked, cfg.edge_weight)
    # confident columns keep their row: the second path leaves and rejoins the first one there
    pinned = good[:, None] & (rr != path.astype(np.float64)[:, None])
    cost_t = np.where(weak[:, None] & outside | pinned, np.float32(1e3), cost_t).astype(np.float32)
    # the path is pinned at every confident column: each stretch between two of them is a path of its own
    path2 = path.copy()
    for idx in _stretches(~good, wrap):
        path2[idx] = _dp_path(np.ascontiguousarray(cost_t[idx]), cfg.max_jump_px, cfg.jump_cost)
    hazy = hazy_ground(lum, chroma, path2) if cfg.chroma_weight > 0 else None
    conf2 = _confidence(np.maximum(edge, hazy_edge), llr, path2, cfg, prior_t, haze_below=True, ground=hazy)
    sky_somewhere = _best_mean_above_t(prior_t, np.ascontiguousarray(path2, dtype=np.int64), 10, 8)
    conf2 = np.minimum(conf2, np.clip((sky_somewhere + 1.0) / 0.3, 0.0, 1.0))
    # a column the path could only reach by leaving the window is not the window's answer
    conf2 = np.where((path2 >= line - window) & (path2 <= line + below), conf2, 0.0)
    return path2, conf2, line


#: A run of at most this many unconfident columns between confident ones is joined to them where
#: its line continues theirs along a strong edge onto ground (:func:`_join_gaps`).
JOIN_GAP_COLUMNS = 4


def _join_gaps(
    rows: np.ndarray,
    conf: np.ndarray,
    edge: np.ndarray,
    llr: np.ndarray,
    cfg: DetectionConfig,
    masked: np.ndarray,
    wrap: bool,
) -> np.ndarray:
    """The confidence with each short run of unconfident columns (at most JOIN_GAP_COLUMNS, confident
    columns on both sides) raised to ``cfg.min_confidence`` where its line continues the line on both
    sides: within ``max_jump_px`` rows of the straight line between them, on an edge of at least
    ``2 min_edge`` onto pixels that look like the learnt ground, and not on a steep run.

    A line along a ridge loses a column or two where a wisp of cloud, the bleed of a steep slope's
    texture into the sky beside it or a compression block spoils one measure; a run that narrow
    cannot hold an occluder's outline the path would have had to climb, and the line through it is
    the one edge its neighbours lie on."""
    h, w = edge.shape
    good = (conf >= cfg.min_confidence) & np.isfinite(rows) & ~masked
    free = ~good & ~masked
    if not free.any() or not good.any():
        return conf
    cols = np.arange(w)
    r = np.clip(np.round(np.nan_to_num(rows, nan=0.0)).astype(np.int64), 0, h - 1)
    strong = np.isfinite(rows) & (edge[r, cols] >= 2 * cfg.min_edge)
    ground = -np.clip(line_band(llr, r, np.arange(2, 10)), -1, 1).mean(axis=0) >= 0.6
    ok = strong & ground & ~_steep_runs(r, cfg)
    out = conf.copy()
    k = JOIN_GAP_COLUMNS
    for idx in _stretches(free, wrap):
        inner = idx[1:-1]
        if inner.size > k or not (good[idx[0]] and good[idx[-1]]) or not ok[inner].all():
            continue
        t = np.arange(1, inner.size + 1) / (inner.size + 1)
        straight = rows[idx[0]] + t * (rows[idx[-1]] - rows[idx[0]])
        # one continuous line from k columns before the run to k columns after it (the line of each
        # column is its own path's: where the second path's line meets the first one's it may step)
        near = np.arange(idx[0] - k, idx[-1] + k + 1)
        near = np.mod(near, w) if wrap else near[(near >= 0) & (near < w)]
        steps = np.abs(np.diff(rows[near]))
        if np.all(np.abs(rows[inner] - straight) <= cfg.max_jump_px) and np.all(steps <= cfg.max_jump_px):
            out[inner] = np.maximum(conf[inner], cfg.min_confidence)
    return out


def _stretches(free: np.ndarray, wrap: bool) -> list[np.ndarray]:
    """The column indices of each run of ``free`` columns with the column before and after it (the
    runs of a full circle may cross its seam; elsewhere the image's ends bound them)."""
    w = free.size
    if free.all():
        return [np.arange(w)]
    # a full circle is read from a column that is not free: no run then crosses the seam
    shift = int(np.argmin(free)) if wrap else 0
    f = np.roll(free, -shift)
    edges = np.diff(np.r_[0, f.astype(np.int8), 0])
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    out = []
    for a, b in zip(starts, ends):
        lo, hi = (a - 1, b + 1) if wrap else (max(a - 1, 0), min(b + 1, w))
        out.append(np.mod(np.arange(lo, hi) + shift, w) if wrap else np.arange(lo, hi) + shift)
    return out


#: A line whose pixels 2-9 rows above score below this on the learnt sky model (-1..1) is doubtful.
DOUBTFUL_SKY = 0.0
#: ... and left out where it lies more than this many band_px rows below the confident columns' line.
DOUBTFUL_DIP_BANDS = 1.25


def _sky_above(llr: np.ndarray, path: np.ndarray) -> np.ndarray:
    """Per column: the mean sky log-likelihood ratio (clipped to +-1) over the rows 2-9 above ``path``."""
    return np.asarray(np.clip(line_band(llr, path, -np.arange(2, 10)), -1, 1).mean(axis=0))


def _learn_llr(
    sm: np.ndarray, texture: np.ndarray, path: np.ndarray, cfg: DetectionConfig, masked: np.ndarray
) -> np.ndarray | None:
    h, w = texture.shape
    rr = np.arange(h)[:, None]
    margin, band = 2, max(4, cfg.band_px)
    use = ~masked[None, :]
    sky_sel = (rr < path[None, :] - margin) & (rr >= path[None, :] - band) & use
    gnd_sel = (rr > path[None, :] + margin) & (rr <= path[None, :] + band) & use
    feats = _features(sm, texture)
    step = max(1, int(sky_sel.sum() // 20000))
    sky = feats[sky_sel][::step]
    step = max(1, int(gnd_sel.sum() // 20000))
    gnd = feats[gnd_sel][::step]
    return _gaussian_llr(feats, sky, gnd)


def _confidence(
    drop: np.ndarray,
    llr: np.ndarray,
    path: np.ndarray,
    cfg: DetectionConfig,
    prior_t: np.ndarray,
    haze_below: bool = False,
    cloud: np.ndarray | None = None,
    ground: np.ndarray | None = None,
) -> np.ndarray:
    """Per column in [0, 1]: sky-like above the line, ground-like below it, and a real edge.

    ``cloud`` (per column, :func:`appliance.vision.skyline_edges.cloud_above`) marks the columns whose
    pixels just above the line are white cloud rather than the learnt clear sky: they count as sky.

    With ``haze_below`` the pixels below the line need not look like the learnt ground, only unlike
    sky and clearly less sky-like than those above it (far terrain seen through haze), or be vouched
    for as ground by other means in ``ground`` (per column in [0, 1]: far ground under haze,
    :func:`appliance.vision.skyline_edges.hazy_ground`; the snow's colour, :func:`_snow_coloured_below`),
    while those above it must look like the learnt sky.
    """
    h, w = drop.shape
    cols = np.arange(w)
    gap, depth = 2, 8
    offs = np.arange(gap, gap + depth)
    sky_above = np.clip(line_band(llr, path, -offs), -1, 1).mean(axis=0)
    ground_below = -np.clip(line_band(llr, path, offs), -1, 1).mean(axis=0)
    edge = drop[np.clip(path, 0, h - 1), cols]
    # a path glued to the window's border found nothing
    inside = (path > gap) & (path < h - 1 - gap)
    # sky just above the skyline is often paler than the sky model: only clearly non-sky (an
    # occluder) fails; the ground below must look like ground
    # a grey cloud or haze resting on the ridge is unlike the learnt sky model too; where the pixels
    # just above are smooth and bright (the generic prior: a cloud, not a rock or a person), a
    # strong edge onto clear ground vouches for the column
    # (the prior's texture bleeds about ten rows across the edge: it is read from 10 to 18 rows up)
    far = np.clip(path[None, :] - np.arange(10, 18)[:, None], 0, h - 1)
    smooth_above = np.clip(prior_t[cols[None, :], far], -1, 1).mean(axis=0)
    strong = np.clip((edge - 2 * cfg.min_edge) / (4 * cfg.min_edge), 0.0, 1.0) * (ground_below > 0.6)
    strong = strong * np.clip(smooth_above / 0.5, 0.0, 1.0)
    c_sky = np.clip(sky_above + 1.2 + 0.6 * strong, 0.0, 1.0)
    if cloud is not None:
        c_sky = np.where(cloud, 1.0, c_sky)
    c_ground = np.clip((ground_below + 0.2) / 0.6, 0.0, 1.0)
    if haze_below:
        contrast = np.clip((sky_above + ground_below - 0.3) / 0.4, 0.0, 1.0) * (ground_below > -0.2)
        c_ground = np.maximum(c_ground, contrast)
        if ground is not None:
            c_ground = np.maximum(c_ground, ground)
        # and the pixels just above must be the learnt sky itself, not a paler band of far terrain
        c_sky = np.minimum(c_sky, np.clip((sky_above - 0.2) / 0.3, 0.0, 1.0))
    c_edge = np.clip(edge / (2 * cfg.min_edge), 0.0, 1.0)
    conf = np.where(inside, np.minimum(np.minimum(c_sky, c_ground), c_edge), 0.0)
    return np.where(_steep_runs(path, cfg), 0.0, conf)


def _steep_runs(path: np.ndarray, cfg: DetectionConfig) -> np.ndarray:
    """Columns where the path climbs or falls at its largest step for a run of columns.

    Terrain seen from afar rarely rises that steeply; the sides of a person, a pole or a rock close
    to the camera do, and the path cannot follow them, so those columns are not to be trusted.
    """
    step = np.abs(np.diff(path.astype(np.int64)))
    at_max = np.concatenate([[False], step >= cfg.max_jump_px])
    out = np.zeros(path.size, dtype=bool)
    run = cfg.max_steep_run_px
    if path.size <= run:
        return out
    # runs of at least `run` consecutive steep steps, widened by `run` columns on both sides
    counts = np.convolve(at_max.astype(np.int64), np.ones(run, dtype=np.int64), mode="same")
    core = counts >= run
    if core.any():
        widened = np.convolve(core.astype(np.int64), np.ones(2 * run + 1, dtype=np.int64), mode="same") > 0
        out |= widened
    return out


def resample(columns: ColumnSkyline, pano: Panorama, step_deg: float) -> Skyline:
    """The skyline at azimuths ``0, step, 2 step...`` from the columns, by linear interpolation.

    An azimuth whose two neighbouring columns are not both valid is missing; so is any azimuth a
    partial panorama does not cover.
    """
    n = int(round(360.0 / step_deg))
    out_az = np.arange(n) * step_deg
    colf = pano.azimuth_to_column(out_az)
    el = np.full(n, np.nan)
    ok = np.isfinite(colf)
    c = np.where(ok, colf, 0.0)
    w = pano.width
    c0 = np.floor(c).astype(np.int64)
    frac = c - c0
    if pano.full_circle:
        i0, i1 = np.mod(c0, w), np.mod(c0 + 1, w)
    else:
        i0, i1 = np.clip(c0, 0, w - 1), np.clip(c0 + 1, 0, w - 1)
    e0, e1 = columns.elevation_deg[i0], columns.elevation_deg[i1]
    val = e0 * (1 - frac) + e1 * frac
    el = np.where(ok & np.isfinite(e0) & np.isfinite(e1), val, np.nan)
    # an azimuth is as trustworthy as the weaker of the two columns it comes from
    conf = np.where(np.isfinite(el), np.clip(np.minimum(columns.confidence[i0], columns.confidence[i1]), 0, 1), 0.0)
    return Skyline(out_az, el, conf)


def detect_skyline(
    pano: Panorama, cfg: DetectionConfig | None = None, mask: list[tuple[float, float]] | None = None
) -> Skyline:
    """The skyline of the panorama, sampled every ``cfg.step_deg`` degrees of azimuth from north."""
    cfg = cfg or DetectionConfig()
    return resample(detect_columns(pano, cfg, mask), pano, cfg.step_deg)


def draw_overlay(pano: Panorama, columns: ColumnSkyline, thickness_px: int = 1) -> np.ndarray:
    """A copy of the panorama with the detected skyline drawn in red (missing columns not drawn)."""
    out = pano.image.copy()
    h = pano.height
    rows = columns.row
    ok = np.isfinite(rows)
    cols = np.arange(pano.width)
    for k in range(-thickness_px + 1, thickness_px):
        r = np.clip(np.round(rows[ok]).astype(np.int64) + k, 0, h - 1)
        out[r, cols[ok]] = (0, 0, 255)
    return out
