"""The skyline over fresh snow: white ground under a pale sky, found by colour where brightness fails.

Snow under a pale sky is often brighter than the sky, so the first brightness drop down a column is
not at the skyline but at the top of the first dark rock in the snow, below it: a line there is
strong false evidence for the estimator ("nothing above this elevation").  The sky/snow boundary is
a step of colour instead (the sky's blue above, neutral white below: blue minus red falls) with the
brightness rising or level, and nothing as blue as the sky anywhere below it.

On plain arrays (an image's rows, the detector's line and confidence); the path itself is run by
:func:`appliance.vision.skyline_detect._snow_rows`:

- the image is snowy when at least 30 % of the ground below the detector's line is bright and
  neutral (:func:`snowy_ground_share`); otherwise nothing changes;
- per pixel, a sky/snow boundary scores by its colour step onto ground not darker than the sky, with
  no sky-blue pixel below it, times its brightness rise (:func:`snow_score`); each column's best
  row is a candidate, trusted where it agrees with its neighbours' and lies above the detector's
  line (or the line was not found there);
- with a quarter of the columns trusted (a snowy image whose snow is darker than its sky, as in the
  Finse photos, has a few candidates on cloud tops only and is left alone), sky and snow models are
  learnt on both sides of the trusted rows (:func:`snow_evidence`: the candidates are placed where
  the brightness first departs from the sky's, :func:`place_rows`); the path is run again with the
  boundary's score beside the brightness drop as its edge and those models as its regions, placed
  where blue minus red crosses halfway from the sky's to the ground's (:func:`colour_rows`) and
  judged there with the colour step onto the snow as an edge too (snow barely brighter than the
  sky has a weak score but a full colour step);
- a line is left out where the pixels just above it have the snow's colour rather than the sky's
  (the top of a rock a few rows below the skyline) or look like the learnt snow, or where it dips
  well below its neighbours (:func:`snow_checks`).  A boundary above a line is not held against
  it: the rocks' tops are caught by those checks, and what stands above a line the path placed
  on the colour step is mostly the top of a white cloud resting on the ridge.  Where a white cloud
  stands behind the ridge the snow has nearly its colour and brightness: outside the capture
  ring's overlaps those azimuths were mostly left out or drawn on the cloud's top;
- white cloud is told from the snow by its colour (:func:`white_cloud`): snow seen through the air
  and lit by the blue sky is bluer than the white cloud behind the ridge.  The snow's own blue minus
  red is learnt below the detector's line (which lies on the ground, at the skyline or on the rocks
  below it; bright neutral pixels away from rocks, whose colour would bleed into the average); white
  pixels clearly less blue than it are cloud, and count as sky in the path as the capture ring's
  moving pixels do (:func:`appliance.vision.skyline_detect._snow_rows`).  Fine texture was tried
  first and does not tell them apart: the twin's clouds carry shading and edges at the snow's scales
  (high-pass energy about 2.5 times the sky's noise against about 3 times for rock-free snow, the
  two spreads overlapping).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from appliance.vision.skyline_pixels import _features, _gaussian_llr, _luma, _texture, _to_float, line_band

#: The image is snowy when at least this share of the ground below the line is bright and neutral.
SNOWY_SHARE = 0.3
#: Bright and neutral: blue-weighted intensity at least this, |blue - red| at most SNOW_MAX_CHROMA.
SNOW_MIN_LUMA = 0.65
SNOW_MAX_CHROMA = 0.08
#: Rows below the line sampled for the snowy-ground share.
GROUND_ROWS = (4, 40)
#: Smallest fall of blue minus red across a candidate (mean of rows 3-8 above less the largest of rows 3-8
#: below: a rock in those rows does not hide the snow beside it).
MIN_CHROMA_STEP = 0.05
#: Below a candidate nothing may be bluer than the bluest of rows 3-8 below it by more than this.
NO_SKY_TOLERANCE = 0.03
#: The brightest of rows 3-8 below a candidate may be darker than the mean of rows 3-8 above by at most this.
MAX_DARKER = 0.03
#: The colour step and the brightness rise (rows +-2) at which a candidate scores fully.
FULL_CHROMA_STEP = 0.08
FULL_RISE = 0.04
MIN_SCORE = 0.5
#: Continuity: a candidate lies within AGREE_PX rows of the median of the candidates within
#: NEIGHBOUR_COLUMNS columns on either side, of which at least half must have one.
NEIGHBOUR_COLUMNS = 10
AGREE_PX = 3.0
#: Rows of the image's top and bottom not searched (the bands measured around a row need them).
EDGE_ROWS = 10
#: A line whose pixels 3-10 rows above look more like the learnt snow than this is left out.
SKY_ABOVE_MIN = 0.3
#: Fewest trusted candidates (and share of the columns) to learn sky and snow from, and the rows
#: above and below them that are learnt from (snow with its rocks).  A snowy image whose skyline is
#: found by the brightness drop (snow darker than the sky) has a few candidates on cloud tops only.
MIN_TRUSTED = 20
TRUSTED_SHARE = 0.25
SKY_ROWS = (3, 12)
SNOW_ROWS = (3, 30)
#: The colour 2-3 rows above a line must lie above this share of the way from the snow's to the sky's.
CHROMA_CUT = 0.35
#: A candidate this many rows or more above the detector's line shows that line to be below the skyline.
STEP_ABOVE_PX = 3.0
#: A line more than DIP_PX rows below the highest line within DIP_COLUMNS columns is left out.
DIP_COLUMNS = 5
DIP_PX = 8.0
#: White cloud (:func:`white_cloud`): blue minus red is averaged over a box this many columns wide and
#: rows high, of pixels all bright and neutral (a rock's colour bleeds into no average); a pixel at
#: least CLOUD_CHROMA_GAP less blue than the snow's median is cloud, in patches at least CLOUD_OPEN_PX
#: (columns, rows) across.
CLOUD_BOX_PX = (15, 3)
CLOUD_CHROMA_GAP = 0.008
CLOUD_OPEN_PX = (9, 5)
#: The cloud marked is carried down by up to CLOUD_GROW_PX rows through pixels whose CLOUD_NARROW_BOX_PX
#: box is as much less blue than the snow.
CLOUD_NARROW_BOX_PX = (7, 3)
CLOUD_GROW_PX = 6
#: A cloud pixel is kept where the sky, or cloud kept, lies within this many rows above it.
CLOUD_HANG_PX = 14
#: Fewest snow pixels to learn the snow's colour from.
CLOUD_MIN_SNOW_PX = 500


def _band_mean(x: np.ndarray, k0: int, k1: int) -> np.ndarray:
    """Per pixel, the mean of ``x`` over rows ``r + k0 .. r + k1`` of its column (clipped to the image)."""
    h = x.shape[0]
    cs = np.zeros((h + 1, x.shape[1]), dtype=np.float64)
    np.cumsum(x, axis=0, dtype=np.float64, out=cs[1:])
    r = np.arange(h)
    a, b = np.clip(r + k0, 0, h), np.clip(r + k1 + 1, 0, h)
    n = np.maximum(b - a, 1)[:, None]
    return np.asarray((cs[b] - cs[a]) / n, dtype=np.float32)


def _band_max(x: np.ndarray, k0: int, k1: int) -> np.ndarray:
    """Per pixel, the largest ``x`` over rows ``r + k0 .. r + k1`` of its column (clipped to the image)."""
    h = x.shape[0]
    out = np.full_like(x, -np.inf)
    for k in range(k0, k1 + 1):
        lo, hi = max(0, -k), min(h, h - k)
        if hi > lo:
            np.maximum(out[lo:hi], x[lo + k : hi + k], out=out[lo:hi])
    return out


def _chroma_luma(f: np.ndarray, lum: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The blurred blue minus red and the luminance of the float image ``f`` (whose luminance is ``lum``), float32."""
    chroma = cv2.GaussianBlur(f[..., 0] - f[..., 2], (0, 0), sigmaX=2.0, sigmaY=0.7)
    return np.asarray(chroma, dtype=np.float32), np.asarray(lum, dtype=np.float32)


def _ground_rows(rows: np.ndarray, h: int) -> np.ndarray:
    """HxW boolean: the pixels GROUND_ROWS below ``rows`` (per column; none where it is not finite)."""
    rr = np.arange(h)[:, None]
    r = np.where(np.isfinite(rows), rows, -10.0 * h)[None, :]
    return (rr >= r + GROUND_ROWS[0]) & (rr <= r + GROUND_ROWS[1])


def _bright_neutral(lum: np.ndarray, chroma: np.ndarray) -> np.ndarray:
    """Per pixel: bright (``lum`` at least SNOW_MIN_LUMA) and neutral (|blue - red| at most SNOW_MAX_CHROMA)."""
    return (lum >= SNOW_MIN_LUMA) & (np.abs(chroma) <= SNOW_MAX_CHROMA)


def snowy_ground_share(f: np.ndarray, lum: np.ndarray, rows: np.ndarray) -> float:
    """The share of the pixels 4-40 rows below ``rows`` (columns with a row) that are bright and neutral, in
    the float image ``f`` whose luminance is ``lum``."""
    sel = _ground_rows(rows, lum.shape[0])
    if not sel.any():
        return 0.0
    return float(_bright_neutral(lum, f[..., 0] - f[..., 2])[sel].mean())


def snow_score(chroma: np.ndarray, lum: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, from the blurred blue minus red and the luminance (:func:`_chroma_luma`): the sky/snow
    boundary's score in [0, 1] (the colour step times the brightness rise, where nothing below is as blue
    as the sky and the ground is not darker), and the colour step's own score in [0, 1] under the same
    conditions (under a pale sky the snow may be no brighter than the sky: no rise, the colour step alone)."""
    h, w = chroma.shape
    lum_h = cv2.blur(lum, (5, 1))
    ca, cb = _band_mean(chroma, -8, -3), _band_max(chroma, 3, 8)
    la, lb = _band_mean(lum_h, -8, -3), _band_max(lum_h, 3, 8)
    step = ca - cb
    # the bluest pixel from three rows below each row down to the image's bottom
    below_max = np.full_like(chroma, -np.inf)
    below_max[:-3] = np.maximum.accumulate(chroma[::-1], axis=0)[::-1][3:]
    ok = (step >= MIN_CHROMA_STEP) & (below_max <= cb + NO_SKY_TOLERANCE) & (lb >= la - MAX_DARKER)
    ok[:EDGE_ROWS] = False
    ok[h - EDGE_ROWS :] = False
    pad = np.concatenate([np.repeat(lum_h[:1], 2, 0), lum_h, np.repeat(lum_h[-1:], 2, 0)])
    rise = pad[4:] - pad[:-4]
    colour = np.clip(step / FULL_CHROMA_STEP, 0.0, 1.0) * ok
    score = colour * np.clip(rise / FULL_RISE, 0.0, 1.0)
    return np.asarray(score, dtype=np.float32), np.asarray(colour, dtype=np.float32)


def snow_candidates(score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per column: the row of the best sky/snow score (NaN: below MIN_SCORE), and that score."""
    w = score.shape[1]
    best = np.argmax(score, axis=0)
    best_score = score[best, np.arange(w)]
    return np.where(best_score >= MIN_SCORE, best.astype(np.float64), np.nan), np.asarray(best_score)


def _agree_with_neighbours(cand: np.ndarray, wrap: bool) -> np.ndarray:
    half = NEIGHBOUR_COLUMNS
    w = cand.size
    if w < 2 * half + 1:
        return np.zeros(w, dtype=bool)
    nan = np.full(half, np.nan)
    p = np.concatenate([cand[-half:], cand, cand[:half]]) if wrap else np.concatenate([nan, cand, nan])
    win = np.lib.stride_tricks.sliding_window_view(p, 2 * half + 1)
    count = np.isfinite(win).sum(axis=1)
    filled = np.where(np.isfinite(win), win, 0.0)
    # the median of the finite ones: sort NaN last and pick the middle of the finite part
    srt = np.sort(np.where(np.isfinite(win), filled, np.inf), axis=1)
    mid = np.clip((count - 1) // 2, 0, 2 * half)
    med = srt[np.arange(w), mid]
    return np.isfinite(cand) & (count >= half) & (np.abs(cand - med) <= AGREE_PX)


def place_rows(lum: np.ndarray, cand: np.ndarray) -> np.ndarray:
    """The fractional row near each candidate where the brightness first departs from the sky's
    (rows 6-9 above) by half its largest departure within rows -5..+4 (pixel centres at integers)."""
    h, w = lum.shape
    cols = np.arange(w)
    lum3 = cv2.blur(lum, (3, 1))
    r0 = np.clip(np.nan_to_num(cand, nan=float(EDGE_ROWS)).astype(np.int64), EDGE_ROWS, h - EDGE_ROWS)
    sky = np.mean([lum3[r0 - k, cols] for k in range(6, 10)], axis=0)
    win = np.stack([lum3[r0 + k, cols] for k in range(-5, 5)])
    dev = np.abs(win - sky[None, :])
    half = 0.5 * dev.max(axis=0)
    first = np.argmax(dev >= half[None, :], axis=0)
    prev = dev[np.maximum(first - 1, 0), cols]
    cur = dev[first, cols]
    frac = np.where(cur > prev, (half - prev) / np.maximum(cur - prev, 1e-6), 0.0)
    return np.asarray(np.where(np.isfinite(cand), r0 - 6 + first + np.clip(frac, 0.0, 1.0), np.nan))


@dataclass(frozen=True)
class SnowEvidence:
    """What a snowy image shows of its sky/snow boundary (HxW maps, per-column rows)."""

    score: np.ndarray  # per pixel: the boundary's score in [0, 1] (:func:`snow_score`)
    colour_step: np.ndarray  # per pixel: the colour step's own score in [0, 1] (:func:`snow_score`)
    llr: np.ndarray  # per pixel: sky-vs-snow log-likelihood ratio of models learnt at the trusted rows
    lum: np.ndarray  # the blue-weighted intensity
    chroma: np.ndarray  # blue minus red, smoothed
    chroma_cut: float  # CHROMA_CUT of the way from the snow's blue minus red to the sky's, at the trusted rows
    cloud: np.ndarray | None = None  # per pixel: white cloud less blue than the snow (:func:`white_cloud`)


def snow_evidence(img8: np.ndarray, rows: np.ndarray, found: np.ndarray, wrap: bool) -> SnowEvidence | None:
    """The snow evidence of an image whose ground below ``rows`` (the detector's line, fractional,
    NaN = none; ``found`` where it is confident) is snowy, from the candidates that agree with
    their neighbours and lie above the line or where it is not found (the boundary's score; in a
    column without one, the colour step alone: snow no brighter than a pale sky shows no rise onto
    it); None where the ground is not snowy or too few candidates are trusted to learn sky and snow
    from (the brightness drop then finds the skyline: snow clearly darker than the sky).  Its
    ``cloud`` is the white cloud told from the snow below the confident line by colour
    (:func:`white_cloud`)."""
    h, w = img8.shape[:2]
    f = _to_float(img8)
    luma = _luma(f)
    if snowy_ground_share(f, luma, rows) < SNOWY_SHARE:
        return None
    chroma, lum = _chroma_luma(f, luma)
    score, colour_step = snow_score(chroma, lum)
    cand, _ = snow_candidates(score)
    cand = np.where(np.isfinite(cand), cand, snow_candidates(colour_step)[0])
    trusted = _agree_with_neighbours(cand, wrap)
    placed = place_rows(lum, np.where(trusted, cand, np.nan))
    line = np.where(np.isfinite(rows), rows, -10.0 * h)
    trusted &= np.isfinite(placed) & (~found | (np.nan_to_num(placed, nan=0.0) < line - STEP_ABOVE_PX))
    if trusted.sum() < max(MIN_TRUSTED, TRUSTED_SHARE * w):
        return None
    feats = _features(f, _texture(luma))
    rr = np.arange(h)[:, None]
    t = np.where(trusted, placed, -10.0 * h)[None, :]
    sky = feats[(rr >= t - SKY_ROWS[1]) & (rr <= t - SKY_ROWS[0])]
    snow = feats[(rr >= t + SNOW_ROWS[0]) & (rr <= t + SNOW_ROWS[1])]
    llr = _gaussian_llr(feats, sky[:: max(1, sky.shape[0] // 20000)], snow[:: max(1, snow.shape[0] // 20000)])
    if llr is None:
        return None
    sky_chroma = float(np.median(chroma[(rr >= t - 8) & (rr <= t - 4)]))
    snow_chroma = float(np.median(chroma[(rr >= t + 4) & (rr <= t + 8)]))
    cloud = white_cloud(f, luma, _ground_rows(np.where(found, rows, np.nan), h))
    return SnowEvidence(score, colour_step, llr, lum, chroma, snow_chroma + CHROMA_CUT * (sky_chroma - snow_chroma),
                        cloud)


def white_cloud(f: np.ndarray, lum: np.ndarray, snow_rows: np.ndarray) -> np.ndarray | None:
    """Per pixel (HxW boolean) of the float image ``f`` (luminance ``lum``): white cloud, told from the
    snow by its colour; None where fewer than CLOUD_MIN_SNOW_PX snow pixels lie in ``snow_rows`` (HxW
    boolean: the ground's rows, below the detector's first line; the candidates the snow pass trusts
    include the tops of white clouds, whose colour would then be learnt as the snow's).

    Blue minus red is averaged over a CLOUD_BOX_PX box whose pixels are all bright and neutral (the
    snowy-ground test's colour: no rock or sky in the box); the snow's is the median of those boxes
    in ``snow_rows``.  A box at least CLOUD_CHROMA_GAP less blue than that is cloud: snow lit by the
    blue sky and seen through the air is bluer than a white cloud (in the camera twin by about 0.015;
    the boxes of rock-free snow lie within 0.007 of their median).  Patches narrower than
    CLOUD_OPEN_PX are dropped (a strip of less blue snow beside a rock); the rest is carried down by
    up to CLOUD_GROW_PX rows through the CLOUD_NARROW_BOX_PX boxes under the same cut (the wide box
    blends the snow beside a sloping ridge into the cloud's lowest rows), and kept where it hangs from
    the sky (:func:`_hanging`: the snow's colour changes with distance, a near slope under a hazier,
    bluer far one is less blue than the snow's median).  A thin cloud's edge, blended
    with the blue sky, takes the snow's colour and is not marked; a snow field whose parts differ in
    colour (sunlit and shaded) may mark its least blue part.
    """
    chroma = f[..., 0] - f[..., 2]
    white = _bright_neutral(lum, chroma).astype(np.uint8)
    box_w, box_h = CLOUD_BOX_PX
    white_box = cv2.erode(white, np.ones((box_h, box_w), np.uint8), borderType=cv2.BORDER_REPLICATE) > 0
    mean = cv2.blur(chroma, (box_w, box_h), borderType=cv2.BORDER_REPLICATE)
    snow = mean[white_box & snow_rows]
    if snow.size < CLOUD_MIN_SNOW_PX:
        return None
    cut = float(np.median(snow)) - CLOUD_CHROMA_GAP
    cloud = (white_box & (mean < cut)).astype(np.uint8)
    open_w, open_h = CLOUD_OPEN_PX
    cloud = cv2.morphologyEx(cloud, cv2.MORPH_OPEN, np.ones((open_h, open_w), np.uint8)) > 0
    narrow_w, narrow_h = CLOUD_NARROW_BOX_PX
    narrow = cv2.blur(chroma, (narrow_w, narrow_h), borderType=cv2.BORDER_REPLICATE) < cut
    narrow &= cv2.erode(white, np.ones((narrow_h, narrow_w), np.uint8), borderType=cv2.BORDER_REPLICATE) > 0
    for _ in range(CLOUD_GROW_PX):
        below = np.zeros_like(cloud)
        below[1:] = cloud[:-1]
        cloud |= below & narrow
    return _hanging(cloud, (lum >= SNOW_MIN_LUMA) & (chroma > SNOW_MAX_CHROMA))


def _hanging(cloud: np.ndarray, sky: np.ndarray) -> np.ndarray:
    """The pixels of ``cloud`` (HxW boolean) joined to the sky above them: down each column from the
    image's top (taken as sky), a cloud pixel is kept where the sky (``sky``) or a kept cloud pixel
    lies within CLOUD_HANG_PX rows above it.  A cloud behind a ridge hangs from the sky, its top
    blended with the blue over a few rows; a patch of less blue snow below a bluer, hazier far slope
    has snow or rocks above it."""
    h, w = cloud.shape
    out = np.zeros_like(cloud)
    gap = np.zeros(w, dtype=np.int64)
    for r in range(h):
        out[r] = cloud[r] & (gap < CLOUD_HANG_PX)
        gap = np.where(sky[r] | out[r], 0, gap + 1)
    return out


def snow_checks(ev: SnowEvidence, rows: np.ndarray, conf: np.ndarray, min_confidence: float,
                wrap: bool, moving_above: np.ndarray | None = None,
                moving_below: np.ndarray | None = None) -> np.ndarray:
    """``conf`` set to 0 where the pixels 3-10 rows above the line at ``rows`` look more like snow
    than sky or those 2-3 rows above it are nearer the snow's colour than the sky's, or where it
    dips more than DIP_PX rows below
    the highest line within DIP_COLUMNS columns (the top of a rock in snow that looks like the sky:
    far snow in haze takes the air's colour).

    Per column (from the capture ring's frames, :func:`appliance.vision.temporal.moving_around`):
    a line with ``moving_below`` (a cloud below it) is left out; one with ``moving_above`` and not
    ``moving_below`` (a drifting white cloud just above, static ground below) is not judged by the
    colour above it."""
    w = ev.llr.shape[1]
    r = np.round(np.nan_to_num(rows, nan=0.0)).astype(np.int64)
    above = np.clip(line_band(ev.llr, r, -np.arange(3, 11)), -1.0, 1.0).mean(axis=0)
    # and just above the line the colour is nearer the sky's than the snow's (a rock a few rows below
    # the skyline has snow just above its top)
    snow_just_above = line_band(ev.chroma, r, -np.arange(2, 4)).mean(axis=0) < ev.chroma_cut
    colour_bad = (above < SKY_ABOVE_MIN) | snow_just_above
    if moving_above is not None and moving_below is not None:
        colour_bad = (colour_bad & ~(moving_above & ~moving_below)) | moving_below
    bad = colour_bad | ~np.isfinite(rows)
    conf = np.where(bad, 0.0, conf)
    k = DIP_COLUMNS
    if w > 2 * k:
        line = np.where(conf >= min_confidence, rows, np.inf)
        inf = np.full(k, np.inf)
        pad = np.concatenate([line[-k:], line, line[:k]]) if wrap else np.concatenate([inf, line, inf])
        highest = np.lib.stride_tricks.sliding_window_view(pad, 2 * k + 1).min(axis=1)
        dip = np.isfinite(line) & (np.where(np.isfinite(line), line, 0.0) - highest > DIP_PX)
        conf = np.where(dip, 0.0, conf)
    return np.asarray(conf)


#: The colour crossing is looked for within this many rows of the placed line; the sky's colour is
#: read COLOUR_SKY_ROWS above it, the snow's COLOUR_SNOW_ROWS below it.
COLOUR_REACH_PX = 3
COLOUR_SKY_ROWS = (5, 9)
COLOUR_SNOW_ROWS = (2, 6)


def colour_rows(chroma: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The fractional row near each of ``rows`` (NaN = none) where blue minus red (``chroma``) first
    falls, from the top, below halfway between the sky's (the mean of rows 5-9 above) and the
    ground's (the median of rows 2-6 below); ``rows`` where it does not within COLOUR_REACH_PX rows.

    Under a pale sky the snow's brightness is near the sky's, and the brightness departure wanders
    a row or two either side of the boundary; the colour step onto the white snow, or onto a dark
    rock standing on the skyline, is there in every column."""
    h, w = chroma.shape
    cols = np.arange(w)
    ok = np.isfinite(rows)
    reach = COLOUR_REACH_PX
    margin = max(COLOUR_SKY_ROWS[1], COLOUR_SNOW_ROWS[1], reach) + 1
    r0 = np.clip(np.round(np.nan_to_num(rows, nan=float(margin))).astype(np.int64), margin, h - 1 - margin)
    sky = np.mean([chroma[r0 - k, cols] for k in range(COLOUR_SKY_ROWS[0], COLOUR_SKY_ROWS[1] + 1)], axis=0)
    ground = np.median([chroma[r0 + k, cols] for k in range(COLOUR_SNOW_ROWS[0], COLOUR_SNOW_ROWS[1] + 1)], axis=0)
    half = 0.5 * (sky + ground)
    win = np.stack([chroma[r0 + k, cols] for k in range(-reach - 1, reach + 1)])
    crossed = win <= half[None, :]
    first = np.argmax(crossed, axis=0)
    found = crossed.any(axis=0) & (first > 0) & (sky - ground >= MIN_CHROMA_STEP)
    prev = win[np.maximum(first - 1, 0), cols]
    cur = win[first, cols]
    frac = np.where(prev > cur, (prev - half) / np.maximum(prev - cur, 1e-6), 0.0)
    # pixel centres at integers: the crossing lies between the rows first - 1 and first of the window
    crossing = r0 - reach - 2 + first + np.clip(frac, 0.0, 1.0)
    return np.asarray(np.where(ok & found, crossing, rows))
