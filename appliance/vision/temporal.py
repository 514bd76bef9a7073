"""Temporal stability across the capture ring: where overlapping frames disagree, something moved.

The capture ring's neighbouring frames share part of their view (``session.capture_overlap``) and
are taken a few seconds apart.  Terrain does not move between them; a cloud drifts.  Each frame is
warped into the panorama (the stitcher knows where it falls), and per panorama pixel that two frames
cover their luminances are compared:

- exposure and vignetting: the second frame's luminance is scaled by a gain that varies smoothly
  across the overlap (a robust quadratic fit, over the overlap's columns, of each column's median
  ratio of the two frames): a change of exposure or the lens's fall-off towards the frame's sides
  does not read as motion, while a cloud drifting over a part of the columns barely moves the fit;
- the measure is an apparent shift in pixels, not a difference of brightness: the difference of the
  two frames is summed (squared, less its noise) over a window along the row and divided by the
  image's squared gradient over the same window (a Lucas-Kanade normal flow without direction).
  An edge misplaced by a fraction of a pixel (the tags' error, bilinear resampling at different
  sub-pixel phases) reads as that fraction, whatever its contrast; a cloud drifting by several
  pixels reads as a shift of a pixel or more (the linear estimate falls short of large shifts);
- noise: both luminances are smoothed (Gaussian, sigma 1 px); the difference's noise is read from
  the overlap's median (most of it agrees) and taken off; where the window's texture is under
  TEXTURE_OVER_NOISE times that noise (a smooth sky, clear or overcast, or a smooth white cloud)
  the texture is taken at that floor: the shift read is then a lower bound, about 0 where the
  frames differ by their noise only (a still smooth sky) and a pixel or more where a smooth cloud
  drifted far enough to change its pixels well beyond the noise (five times its energy);
- the window runs along the row only: across the skyline it would lend a cloud's motion to the
  ridge below it.

The result (:func:`frame_disagreement`) is a float32 map of that shift (px): about 0 where the
frames agree, NaN where fewer than two frames cover the pixel.  At least
MOVING_SHIFT_PX (:func:`moving_pixels`) it is evidence that the pixel is sky (a cloud moved), never
is a small one evidence of ground: a clear blue sky does not move either.  On the camera twin's
snow scenes under 0.1 % of the terrain's pixels read over 0.5 px.  A panorama read from a file, or
made of one photo, has no map; detection then works as without it.

Caveats: a near object seen from a camera that does not turn about its optical centre shifts by
its parallax, and a cloud with no texture (a smooth white heap) shows no shift: motion is used as
sky evidence only, beside colour and brightness, where the frames overlap.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from appliance.vision.skyline_pixels import intensity

#: The smallest noise (luminance, 0..1) assumed of a frame difference, whatever the overlap shows.
NOISE_FLOOR = 0.002
#: Horizontal Gaussian window (px) over which the difference and the texture are summed.
WINDOW_SIGMA_PX = 4.0
#: Where the texture's gradient (rms per pixel) is below this multiple of the difference's noise, the
#: apparent shift cannot be measured: it is taken as none (a smooth sky, clear or overcast).
TEXTURE_OVER_NOISE = 2.0
#: Pixels this close to a frame's border are not compared (interpolation against the border).
BORDER_PX = 2
#: Fewest overlapping pixels (and columns) for a pair's gain to be fitted.
MIN_OVERLAP_PX = 200
MIN_OVERLAP_COLUMNS = 8


def luminance(image: np.ndarray) -> np.ndarray:
    """The smoothed luminance (0..1, float32) of an HxWx3 uint8 BGR image, as frames are compared."""
    return np.asarray(cv2.GaussianBlur(intensity(image), (0, 0), sigmaX=1.0), dtype=np.float32)


def _gain(a: np.ndarray, b: np.ndarray, both: np.ndarray, cols: np.ndarray) -> np.ndarray | None:
    """Per column of ``cols`` (those with overlap), the smooth gain that takes ``b`` onto ``a``
    (a quadratic in the column through the columns' median ratios, refitted once without outliers)."""
    ratios, xs = [], []
    for c in cols:
        sel = both[:, c] & (b[:, c] > 0.03) & (a[:, c] > 0.03)
        if sel.sum() >= 8:
            ratios.append(float(np.median(a[sel, c] / b[sel, c])))
            xs.append(float(c))
    if len(xs) < MIN_OVERLAP_COLUMNS:
        return None
    x, y = np.asarray(xs), np.asarray(ratios)
    x0, span = x.mean(), max(float(np.ptp(x)), 1.0)
    deg = 2 if len(xs) >= 3 * MIN_OVERLAP_COLUMNS else 1
    coef = np.polyfit((x - x0) / span, y, deg)
    resid = np.abs(y - np.polyval(coef, (x - x0) / span))
    keep = resid <= max(3.0 * float(np.median(resid)), 0.01)
    if keep.sum() > deg + 2:
        coef = np.polyfit((x[keep] - x0) / span, y[keep], deg)
    return np.asarray(np.polyval(coef, (cols.astype(np.float64) - x0) / span), dtype=np.float32)


def _pair(a: np.ndarray, b: np.ndarray, both: np.ndarray, rolled: bool = False) -> np.ndarray | None:
    """The apparent shift (px, HxW float32, NaN outside ``both``) between two warped luminance maps
    over their overlap ``both``; None where the overlap is too small to fit the gain."""
    if both.sum() < MIN_OVERLAP_PX:
        return None
    cols = np.flatnonzero(both.any(axis=0))
    gaps = np.diff(cols)
    if gaps.size and gaps.max() > 1 and not rolled:
        # an overlap across a full circle's seam (column 0) is compared with the seam rolled away
        shift = -int(cols[int(np.argmax(gaps)) + 1])
        d = _pair(np.roll(a, shift, axis=1), np.roll(b, shift, axis=1), np.roll(both, shift, axis=1), True)
        return None if d is None else np.roll(d, -shift, axis=1)
    lo, hi = int(cols.min()), int(cols.max()) + 1
    a_s, b_s, m = a[:, lo:hi], b[:, lo:hi], both[:, lo:hi]
    gain = _gain(a_s, b_s, m, cols - lo)
    if gain is None:
        return None
    g = np.ones(hi - lo, np.float32)
    g[cols - lo] = gain
    b_s = b_s * g[None, :]
    it = np.where(m, a_s - b_s, 0.0).astype(np.float32)
    mean = 0.5 * (a_s + b_s)
    gx, gy = cv2.Sobel(mean, cv2.CV_32F, 1, 0, ksize=3) / 8, cv2.Sobel(mean, cv2.CV_32F, 0, 1, ksize=3) / 8
    grad2 = gx * gx + gy * gy
    # the difference's own noise (both frames'), from the overlap's median: most of it agrees
    noise2 = max(float((1.4826 * np.median(np.abs(it[m]))) ** 2), NOISE_FLOOR**2)
    # along the row only: a window across the skyline would lend the cloud's motion to the ridge below it
    e_t = cv2.GaussianBlur(it * it, (0, 0), sigmaX=WINDOW_SIGMA_PX, sigmaY=0.5)
    e_g = cv2.GaussianBlur(np.where(m, grad2, 0.0).astype(np.float32), (0, 0), sigmaX=WINDOW_SIGMA_PX, sigmaY=0.5)
    # where the texture is too faint to measure a shift, it is taken at that floor: the shift read is
    # then a lower bound (a smooth cloud that drifted far enough to change its pixels well beyond the
    # noise still reads as moving; a smooth still sky differs by its noise only and reads as none)
    shift = np.sqrt(np.maximum(e_t - noise2, 0.0) / np.maximum(e_g, TEXTURE_OVER_NOISE**2 * noise2))
    d = np.where(m, shift, np.nan).astype(np.float32)
    out = np.full(a.shape, np.nan, np.float32)
    out[:, lo:hi] = d
    return out


def frame_disagreement(warped: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """The per-pixel apparent shift (px, float32; the largest over the pairs of frames; NaN where
    fewer than two frames are compared) of frames warped into one panorama: ``warped`` holds, per
    frame, its luminance (:func:`luminance` of the warped image) and where it covers the panorama
    (boolean)."""
    if not warped:
        raise ValueError("frame_disagreement: no frames")
    shape = warped[0][0].shape
    kernel = np.ones((2 * BORDER_PX + 1, 2 * BORDER_PX + 1), np.uint8)
    inner = [cv2.erode(cov.astype(np.uint8), kernel, borderType=cv2.BORDER_REPLICATE) > 0 for _, cov in warped]
    out = np.full(shape, np.nan, np.float32)
    spans = [np.flatnonzero(m.any(axis=0)) for m in inner]
    for i in range(len(warped)):
        for j in range(i + 1, len(warped)):
            if spans[i].size == 0 or spans[j].size == 0 or not np.intersect1d(spans[i], spans[j]).size:
                continue
            both = inner[i] & inner[j]
            d = _pair(warped[i][0], warped[j][0], both)
            if d is None:
                continue
            np.fmax(out, d, out=out)
    return out


#: A pixel whose apparent shift between frames is at least this (px) moved: a cloud drifting (the
#: tags' misregistration and resampling stay well under it on terrain).
MOVING_SHIFT_PX = 1.0
#: Rows above a line searched for moving pixels (sky there: the line is at most about this far below
#: the skyline), and rows below it (a cloud, not ground).
ABOVE_ROWS = (1, 5)
BELOW_ROWS = (2, 14)
#: Fewest moving pixels below a line that put the line on a cloud.
MIN_BELOW_PX = 2


def moving_pixels(motion: np.ndarray) -> np.ndarray:
    """Where a shift map (:func:`frame_disagreement`, px) shows a pixel moved (boolean, HxW)."""
    return np.asarray(np.nan_to_num(motion, nan=0.0) >= MOVING_SHIFT_PX)


def _column_sums(moving: np.ndarray) -> np.ndarray:
    """(H+1)xW: per column, how many moving pixels lie above each row (row 0's 0 included)."""
    cs = np.zeros((moving.shape[0] + 1, moving.shape[1]), np.int32)
    np.cumsum(moving, axis=0, dtype=np.int32, out=cs[1:])
    return cs


def _in_band(sums: np.ndarray, rows: np.ndarray | None, k0: int, k1: int) -> np.ndarray:
    """How many moving pixels lie in rows ``r + k0 .. r + k1`` of their column (rows off the image count
    none), from :func:`_column_sums`: per column for integer rows ``r`` (one per column), or HxW for every
    row of the image (``rows`` None)."""
    h = sums.shape[0] - 1
    if rows is None:  # whole rows gathered: the image's every row at once
        r = np.arange(h)
        return np.asarray(sums[np.clip(r + k1 + 1, 0, h)] - sums[np.clip(r + k0, 0, h)])
    cols = np.arange(sums.shape[1])
    return np.asarray(sums[np.clip(rows + k1 + 1, 0, h), cols] - sums[np.clip(rows + k0, 0, h), cols])


def moving_around(moving: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per column, for a line at fractional ``rows`` (NaN = none): whether a moving pixel lies within
    ABOVE_ROWS rows above it, and whether at least MIN_BELOW_PX lie within BELOW_ROWS rows below it."""
    ok = np.isfinite(rows)
    r = np.round(np.nan_to_num(rows, nan=0.0)).astype(np.int64)
    sums = _column_sums(moving)
    above = ok & (_in_band(sums, r, -ABOVE_ROWS[1], -ABOVE_ROWS[0]) > 0)
    below = ok & (_in_band(sums, r, *BELOW_ROWS) >= MIN_BELOW_PX)
    return above, below


def cloud_below(moving: np.ndarray) -> np.ndarray:
    """Per pixel (HxW boolean): whether at least MIN_BELOW_PX moving pixels lie within BELOW_ROWS
    rows below it (:func:`moving_around`'s test of a line, at every row): an edge there is the top of
    a drifting cloud, not the ground's."""
    return np.asarray(_in_band(_column_sums(moving), None, *BELOW_ROWS) >= MIN_BELOW_PX)


#: The rows above (moving pixels there) and below (none there) a pixel that make it the bottom of a
#: moving cloud (:func:`motion_edge`).
EDGE_ABOVE_ROWS = (1, 4)
EDGE_BELOW_ROWS = (1, 3)


def motion_edge(moving: np.ndarray) -> np.ndarray:
    """Per pixel in {0, 1} (float32): 1 where the pixel is still, moving pixels lie within
    EDGE_ABOVE_ROWS rows above it and none within EDGE_BELOW_ROWS rows below: the lower edge of a
    drifting cloud against still ground (a white cloud behind a snowy ridge, whatever the brightness
    of its base against the snow's)."""
    sums = _column_sums(moving)
    at_bottom = (_in_band(sums, None, -EDGE_ABOVE_ROWS[1], -EDGE_ABOVE_ROWS[0]) > 0) & (
        _in_band(sums, None, *EDGE_BELOW_ROWS) == 0)
    return np.asarray(at_bottom & ~moving, dtype=np.float32)
