"""Per-pixel work of skyline detection on plain arrays (no settings, no panorama geometry):
intensity, texture and colour features, a generic sky prior and the sky/ground log-likelihood of
Gaussian colour models, each pixel's cost for the dynamic programme and its minimum-cost path.

The per-pixel costs are built column-major (band sums by cumulative sums), the dynamic programme
steps a column at a time over a sliding window of rows in float32 without back-pointers, and the
Gaussian models are evaluated per pixel by ``cv2.transform`` (an affine map, then a sum of squares);
plain numpy and OpenCV (DESIGN.md, "Decisions").
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

MAX_NOISE_TEXTURE = 0.006  # a texture floor above this is not sky: the image has none


# ----------------------------------------------------------------------------- features


def _to_float(image: np.ndarray) -> np.ndarray:
    return image.astype(np.float32) * np.float32(1.0 / 255.0)


def intensity(img8: np.ndarray) -> np.ndarray:
    """The intensity (0..1, float32) the detector's brightness drop and the frames' comparison are made
    of, of an HxWx3 uint8 BGR image: 0.3 blue, 0.35 green, 0.35 red."""
    weights = np.array([[0.3, 0.35, 0.35]], dtype=np.float32) / np.float32(255.0)
    return np.asarray(cv2.transform(img8.astype(np.float32), weights), dtype=np.float32)


def _luma(bgr: np.ndarray) -> np.ndarray:
    """A blue-weighted intensity: the sky/ground contrast is strongest in blue."""
    return np.asarray(0.5 * bgr[..., 0] + 0.35 * bgr[..., 1] + 0.15 * bgr[..., 2], dtype=np.float32)


def _downward_drop(lum: np.ndarray) -> np.ndarray:
    """Intensity of the row above minus the row below (positive where bright sky is above)."""
    drop = np.zeros_like(lum)
    drop[1:-1] = lum[:-2] - lum[2:]
    return drop


def _texture(lum: np.ndarray) -> np.ndarray:
    gx = cv2.Sobel(lum, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(lum, cv2.CV_32F, 0, 1, ksize=3)
    mag = np.abs(gx) + np.abs(gy)
    return np.asarray(cv2.blur(mag, (5, 5)) * np.float32(0.125), dtype=np.float32)


def _sky_prior(bgr: np.ndarray, texture: np.ndarray) -> np.ndarray:
    """Generic sky likeness in [-1, 1]: smooth and bright.

    Smooth is relative to the image's own noise floor (its 10th percentile of texture, usually
    sky, over the pixels that have any), so the prior adapts to sensor noise and compression.
    Colour is left to the models learnt per image: hazy terrain may be bluer than the sky above it.
    """
    sample = texture[::4, ::4]
    # pixels without any texture (black padding where no photo reached, a clipped sky) carry no
    # noise to measure: with them a band of padding would set the floor to nothing
    live = sample[sample > 0]
    floor = float(np.percentile(live if live.size >= sample.size // 4 else sample, 10))
    floor = min(max(floor, 1e-4), MAX_NOISE_TEXTURE)
    smooth = np.clip(1.0 - (texture - 1.5 * floor) / (3.0 * floor), 0.0, 1.0)
    v = np.maximum(np.maximum(bgr[..., 0], bgr[..., 1]), bgr[..., 2])
    bright = np.clip((v - 0.3) / 0.25, 0.0, 1.0)
    return np.asarray(2.0 * smooth * bright - 1.0, dtype=np.float32)


def _features(bgr: np.ndarray, texture: np.ndarray) -> np.ndarray:
    """Per pixel (HxWx4 float32): blue, green, red and the (capped, scaled) texture."""
    tex = np.minimum(texture, np.float32(0.2)) * np.float32(3.0)
    return np.asarray(cv2.merge([bgr[..., 0], bgr[..., 1], bgr[..., 2], tex]))


def _gaussian_llr(feats: np.ndarray, sky: np.ndarray, ground: np.ndarray) -> np.ndarray | None:
    """Log-likelihood ratio sky vs ground of each feature pixel (HxWx4), from Gaussian models; clipped to +-4."""
    if sky.shape[0] < 50 or ground.shape[0] < 50:
        return None
    out = np.zeros(feats.shape[:2], dtype=np.float32)
    ones = np.ones((1, feats.shape[2]), dtype=np.float32)
    for sign, sample in ((1.0, sky), (-1.0, ground)):
        # the covariance by OpenCV, not np.cov (DESIGN.md, "Decisions")
        flags = cv2.COVAR_NORMAL | cv2.COVAR_ROWS | cv2.COVAR_SCALE
        cov, mean = cv2.calcCovarMatrix(sample, np.empty((0, 0), np.float64), flags, ctype=cv2.CV_64F)
        mu = mean[0]
        cov = cov * (sample.shape[0] / (sample.shape[0] - 1.0)) + np.eye(sample.shape[1]) * 1e-4
        # Mahalanobis distance as a squared norm: with inv(cov) = L L^T, |L^T (x - mu)|^2, the affine
        # map applied per pixel by cv2.transform (one pass, no temporaries per feature)
        lt = np.linalg.cholesky(np.linalg.inv(cov)).T
        affine = np.hstack([lt, -(lt @ mu)[:, None]]).astype(np.float32)
        y = cv2.transform(feats, affine)
        maha = cv2.transform(y * y, ones)
        logdet = float(np.linalg.slogdet(cov)[1])
        out -= np.float32(sign * 0.5) * (maha + np.float32(logdet))
    return np.clip(out / np.float32(4.0), -4.0, 4.0)


# ----------------------------------------------------------------------------- dynamic programming


def _dp_path(cost_t: np.ndarray, max_jump: int, jump_cost: float) -> np.ndarray:
    """Row per column minimising sum(cost_t[c, row]) + jump_cost * sum |row step|; cost_t is WxH.

    The forward pass keeps every column's accumulated cost (float32, shifted by its minimum at each
    column so that float32 keeps its precision).  A column is one step: the previous column's costs,
    seen from each row through a sliding window of the 2 max_jump + 1 rows around it (a view, no
    copy), plus the jump penalties, reduced by their minimum.  No back-pointers are stored: the
    backward pass recomputes the best predecessor of the path's row only, with the forward pass's
    arithmetic and the first minimum in increasing row order (the uppermost row) on ties.
    """
    w, h = cost_t.shape
    cost = np.asarray(cost_t, dtype=np.float32)
    m = int(max_jump)
    pen = np.array([jump_cost * abs(d) for d in range(-m, m + 1)], dtype=np.float32)
    padded = np.full(h + 2 * m, np.inf, dtype=np.float32)
    reach = sliding_window_view(padded, h)  # reach[k, r] = previous column's cost at row r + k - m
    stepped = np.empty((2 * m + 1, h), dtype=np.float32)
    accs = np.empty((w, h), dtype=np.float32)
    accs[0] = cost[0]
    for c in range(1, w):
        padded[m : m + h] = accs[c - 1]
        np.add(reach, pen[:, None], out=stepped)
        cur = accs[c]
        np.minimum.reduce(stepped, axis=0, out=cur)
        cur -= cur.min()
        cur += cost[c]
    path = np.empty(w, dtype=np.int32)
    r = int(np.argmin(accs[w - 1]))
    path[w - 1] = r
    for c in range(w - 1, 0, -1):
        lo, hi = max(0, r - m), min(h, r + m + 1)
        r = lo + int(np.argmin(accs[c - 1, lo:hi] + pen[lo - r + m : hi - r + m]))
        path[c - 1] = r
    return path


def _cost_columns(
    llr_t: np.ndarray, edge_t: np.ndarray, masked: np.ndarray, band: int, edge_weight: float
) -> np.ndarray:
    """Per column (WxH, from transposed WxH inputs): region term minus weighted edge term.

    Region: (sum of clip(llr) over the ``band`` rows from the pixel down) minus (the same over the
    ``band`` rows above it), divided by ``band``: -2 (sky above, ground below) .. +2, from cumulative
    sums in float64.  Edge: the downward drop, saturating at 0.1.  Masked columns cost nothing.
    """
    w, h = llr_t.shape
    # cumulative sums padded by ``band`` copies of their ends, so that every clamped window end is a slice
    cs = np.empty((w, h + 1 + 2 * band), dtype=np.float64)
    cs[:, band] = 0.0
    np.cumsum(np.clip(llr_t, -1.0, 1.0), axis=1, dtype=np.float64, out=cs[:, band + 1 : band + h + 1])
    cs[:, :band] = 0.0
    cs[:, band + h + 1 :] = cs[:, band + h : band + h + 1]
    here = cs[:, band : band + h]
    out64 = cs[:, 2 * band : 2 * band + h] - here  # the band below
    out64 -= here - cs[:, :h]  # the band above
    out64 *= 1.0 / band
    edge = np.asarray(edge_t, dtype=np.float64) * 10.0
    np.clip(edge, 0.0, 1.0, out=edge)
    edge *= edge_weight
    out64 -= edge
    out = out64.astype(np.float32)
    out[np.asarray(masked, dtype=bool)] = 0.0
    return out


def line_band(x: np.ndarray, rows: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """``x`` (HxW) at each of ``offsets`` rows from the line at ``rows`` (integer, per column; negative
    offsets above it), clipped to the image: (len(offsets), W), in the offsets' order."""
    h, w = x.shape[:2]
    rr = np.clip(np.asarray(rows)[None, :] + np.asarray(offsets)[:, None], 0, h - 1)
    return np.asarray(x[rr, np.arange(w)[None, :]])


def _best_mean_above_t(score_t: np.ndarray, path: np.ndarray, gap: int, depth: int) -> np.ndarray:
    """Per column of the transposed (WxH) ``score_t``, the largest mean of the score (clipped to
    [-1, 1]) over ``depth`` consecutive rows lying wholly at least ``gap`` rows above the path; -1
    where no such run of rows fits.  A running sum down the rows, every column at once."""
    w, h = score_t.shape
    rows = np.ascontiguousarray(np.clip(score_t, -1.0, 1.0).T, dtype=np.float64)  # HxW
    last = np.minimum(np.asarray(path, dtype=np.int64) - gap, h - 1)  # the lowest row a window may reach
    run = np.zeros(w)
    for r in range(min(depth, h)):
        run += rows[r]
    best = run.copy()
    for r in range(depth, h):
        run += rows[r] - rows[r - depth]
        np.maximum(best, run, out=best, where=r <= last)
    return np.where(last - depth + 1 < 0, -1.0, best / depth)
