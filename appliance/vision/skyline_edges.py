"""Edge shape at a skyline candidate: how sharp the step is, and whether it is a bright-over-dark
step onto ground; per column, on plain arrays (a panorama's rows, no settings object).

A ridge against the sky is a silhouette: its step is made within a pixel or two.  The lower edge of
a cloud bank resting on a ridge fades over a degree or more, and a line drawn there lies below the
hidden skyline (false evidence for the estimator: "nothing above this elevation").  These measures
let the detector leave such columns out.

A cumulus behind a ridge is the other way round: white cloud just above a sharp step onto dark
ground (:func:`cloud_above`), unlike the clear sky the image's sky model was learnt on, yet no
occluder; such columns are trusted where they continue the line found under clear sky on both
sides (:func:`anchored`).
"""

from __future__ import annotations

import cv2
import numpy as np

from appliance.vision.skyline_pixels import _downward_drop, _luma, _to_float, line_band


def horizontal_luma(img8: np.ndarray) -> np.ndarray:
    """The blue-weighted intensity averaged over a few columns but not across rows (0..1)."""
    return np.asarray(cv2.blur(_luma(_to_float(img8)), (7, 1)), dtype=np.float32)


def slope_ratio(lum_h: np.ndarray, rows: np.ndarray, far_px: int) -> np.ndarray:
    """Per column: the intensity's mean fall per row over the rows 3 to ``far_px`` above ``rows``,
    over its fall per row across the line (rows -1 to +1).  About 0.1 or less at a silhouette (the
    sky above it is flat beside the step, even under a shaded cloud); 0.4 and more at an edge that
    fades over ten rows or more.  NaN where there is no fall across the line."""
    h, w = lum_h.shape
    cols = np.arange(w)
    r = np.clip(np.round(np.nan_to_num(rows, nan=0.0)).astype(np.int64), 0, h - 1)

    def at(k: int) -> np.ndarray:
        return lum_h[np.clip(r + k, 0, h - 1), cols].astype(np.float64)

    edge = (at(-1) - at(1)) / 2.0
    above = (at(-far_px) - at(-3)) / (far_px - 3)
    return np.asarray(np.where(edge > 1e-4, above / np.where(edge > 1e-4, edge, 1.0), np.nan))


def sharpness_confidence(lum_h: np.ndarray, rows: np.ndarray, far_px: int, min_edge: float,
                         max_slope_ratio: float) -> np.ndarray:
    """Per column in [0, 1]: how sharp the intensity step at ``rows`` is.

    A ridge against the sky is a step a pixel or two wide; the lower edge of a cloud resting on a
    ridge (the ridge hidden behind it) fades over a degree or more: the intensity still falls in the
    rows above the line nearly as fast as across it (:func:`slope_ratio`).  Confidence is 1 for a
    ratio below ``max_slope_ratio - 0.15`` and 0 above ``max_slope_ratio``.  A weak step (below
    ``2 min_edge``) is not judged (its column stands or falls on its edge strength).
    """
    h, w = lum_h.shape
    cols = np.arange(w)
    r = np.clip(np.round(np.nan_to_num(rows, nan=0.0)).astype(np.int64), 0, h - 1)
    above_far = lum_h[np.clip(r - far_px, 0, h - 1), cols]
    judged = above_far - lum_h[np.clip(r + 2, 0, h - 1), cols] >= 2 * min_edge
    ratio = np.where(judged, np.nan_to_num(slope_ratio(lum_h, rows, far_px), nan=0.0), 0.0)
    # a cloud's base runs along the azimuths: the ratio is averaged over neighbouring columns, and a
    # column near a diffuse stretch is not trusted either
    ratio = _running(ratio, SHARPNESS_AVERAGE_COLUMNS, np.mean)
    c = np.clip((max_slope_ratio - ratio) / 0.15, 0.0, 1.0)
    return _running(c, SHARPNESS_SPREAD_COLUMNS, np.min)


#: Columns over which the sharpness share is averaged, and over which a diffuse edge spreads distrust.
SHARPNESS_AVERAGE_COLUMNS = 9
SHARPNESS_SPREAD_COLUMNS = 1


def _running(x: np.ndarray, n: int, reduce) -> np.ndarray:  # type: ignore[no-untyped-def]
    """``reduce`` (np.mean or np.min) over a window of ``n`` columns centred on each (ends reflected)."""
    half = n // 2
    if x.size <= half:
        return x
    p = np.pad(x, half, mode="reflect")
    return np.asarray(reduce(np.lib.stride_tricks.sliding_window_view(p, n), axis=-1))


#: A line within this many rows of the padding (no photo reached there) is the padding's edge.
VOID_MARGIN_PX = 4


def fill_void(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The image with its padding (pixels exactly black in every channel from the top or bottom edge
    of a column, where no photo reached)
    replaced by the nearest covered pixel above it in the column (below it at the top), and the
    padding's mask.  Without it the padding's border is the strongest edge of a bright scene."""
    black = np.all(image == 0, axis=-1)
    # only black reaching the image's top or bottom edge: black shadows inside a photo are scene
    void = np.logical_and.accumulate(black, axis=0) | np.logical_and.accumulate(black[::-1], axis=0)[::-1]
    if not void.any():
        return image, void
    h = image.shape[0]
    idx = np.where(~void, np.arange(h)[:, None], -1)
    down = np.maximum.accumulate(idx, axis=0)  # the last covered row at or above each pixel
    up_idx = np.where(~void, np.arange(h)[:, None], h)
    up = np.minimum.accumulate(up_idx[::-1], axis=0)[::-1]  # the first covered row at or below
    src = np.where(down >= 0, down, np.where(up < h, up, np.arange(h)[:, None]))
    cols = np.broadcast_to(np.arange(image.shape[1])[None, :], src.shape)
    return np.ascontiguousarray(image[src, cols]), void


def near_rows(mask: np.ndarray, rows: np.ndarray, margin_px: int) -> np.ndarray:
    """Per column: whether ``mask`` (HxW) is set within ``margin_px`` rows of ``rows`` (NaN: False)."""
    h, w = mask.shape
    if not mask.any():
        return np.zeros(w, dtype=bool)
    cols = np.arange(w)
    r = np.round(np.nan_to_num(rows, nan=-10 * h)).astype(np.int64)
    out = np.zeros(w, dtype=bool)
    for k in range(-margin_px, margin_px + 1):
        rk = r + k
        inside = (rk >= 0) & (rk < h)
        out |= inside & mask[np.clip(rk, 0, h - 1), cols]
    return out



def blue_minus_red(img8: np.ndarray, smooth_sigma_px: float) -> np.ndarray:
    """Blue minus red (-1..1, float32) of an HxWx3 uint8 BGR image, smoothed as the intensity is."""
    chroma = cv2.transform(img8.astype(np.float32), np.array([[1.0, 0.0, -1.0]], np.float32) / np.float32(255.0))
    return np.asarray(cv2.GaussianBlur(chroma, (0, 0), sigmaX=0.7, sigmaY=smooth_sigma_px), dtype=np.float32)


def colour_edge(drop: np.ndarray, chroma: np.ndarray, chroma_weight: float) -> np.ndarray:
    """The edge a column's confidence asks for: the intensity ``drop``, or the drop of blue minus red
    (``chroma``, :func:`blue_minus_red`, times ``chroma_weight``) where that is larger: white snow under
    a pale sky is brighter than the sky, yet less blue.  (The path itself follows the intensity drop:
    the top of a white cloud on blue sky is such a colour edge too.)"""
    if chroma_weight <= 0:
        return drop
    return np.asarray(np.maximum(drop, np.float32(chroma_weight) * _downward_drop(chroma)))


def haze_edge(drop: np.ndarray, chroma: np.ndarray, chroma_weight: float) -> np.ndarray:
    """The edge of far ground under haze: the rise of blue minus red (``chroma``) down a column,
    times ``chroma_weight``, where the intensity drops too (0 elsewhere).

    Near the horizon the sky is whitened by the air it is seen through; far ground seen through the
    same air is darker and bluer than that sky (the haze's light over a dark background), and it
    turns bluer still the moment the sky ends.  Its brightness drop alone is faint."""
    rise = np.maximum(-_downward_drop(chroma), np.float32(0.0)) * np.float32(chroma_weight)
    return np.asarray(np.where(drop > 0, np.maximum(drop, rise), drop), dtype=np.float32)


#: Far ground under haze (:func:`hazy_ground`): the rows 2-9 below a line darker than those above by
#: HAZE_DARKER and bluer (blue minus red) by HAZE_BLUER at full score, and the rows HAZE_FAR_ROWS below
#: darker again than the rows 2-9 below by HAZE_DARKER / 2.
HAZE_DARKER = 0.04
HAZE_BLUER = 0.05
HAZE_FAR_ROWS = (10, 30)


def haze_reversal(lum: np.ndarray, chroma: np.ndarray, near_px: int, far_px: int) -> np.ndarray:
    """Per pixel in [0, 1]: how much darker and bluer it is than the mean of the pixels ``near_px`` to
    ``far_px`` rows above it (full score at HAZE_DARKER and HAZE_BLUER).

    Down a column the sky brightens and whitens towards the horizon; far ground under haze is darker
    and bluer than the whitened sky above it, however much its colour resembles the sky's higher up.
    Sky shows the reversal only under something whiter than itself (a cloud's base, glare)."""
    h = lum.shape[0]
    n = far_px - near_px + 1
    k = (far_px + near_px) // 2
    out = np.zeros_like(lum)
    if h <= far_px:
        return out
    # the box mean centred k rows above each pixel (n is odd: far_px and near_px differ by an even number)
    l_up = cv2.blur(lum, (1, n), borderType=cv2.BORDER_REPLICATE)
    c_up = cv2.blur(chroma, (1, n), borderType=cv2.BORDER_REPLICATE)
    darker = np.clip((l_up[:-k] - lum[k:]) * np.float32(1.0 / HAZE_DARKER), 0.0, 1.0)
    bluer = np.clip((chroma[k:] - c_up[:-k]) * np.float32(1.0 / HAZE_BLUER), 0.0, 1.0)
    out[k:] = np.minimum(darker, bluer)
    return out


def hazy_ground(lum: np.ndarray, chroma: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Per column in [0, 1]: how much the pixels below ``rows`` (integer rows per column) look like far
    ground under haze rather than more sky: darker and bluer than the pixels just above the line (the
    whitened sky at the horizon), and darker still further down (the ground nears and the haze in
    front of it thins).  Sky under a cloud's base is darker and bluer than the cloud too, but brightens
    towards the horizon below it."""
    h = lum.shape[0]
    r = np.asarray(rows, dtype=np.int64)

    def band(x: np.ndarray, k0: int, k1: int) -> np.ndarray:
        return np.asarray(line_band(x, r, np.arange(k0, k1 + 1)).mean(axis=0), dtype=np.float64)

    l_up, l_dn, l_far = band(lum, -9, -2), band(lum, 2, 9), band(lum, *HAZE_FAR_ROWS)
    c_up, c_dn = band(chroma, -9, -2), band(chroma, 2, 9)
    darker = np.clip((l_up - l_dn) / HAZE_DARKER, 0.0, 1.0)
    bluer = np.clip((c_dn - c_up) / HAZE_BLUER, 0.0, 1.0)
    nearer = np.clip((l_dn - l_far) / (0.5 * HAZE_DARKER), 0.0, 1.0)
    inside = (r - 9 >= 0) & (r + HAZE_FAR_ROWS[1] < h)
    return np.asarray(np.where(inside, np.minimum(np.minimum(darker, bluer), nearer), 0.0))


#: Cloud above a line: rows CLOUD_ROWS above it all at least CLOUD_MIN_VALUE bright (largest channel),
#: not warmer than neutral (blue minus red at least CLOUD_MIN_BLUE), white somewhere (blue minus red at
#: most CLOUD_MAX_BLUE) and, on average, CLOUD_MIN_CONTRAST brighter than the same rows below it.
CLOUD_ROWS = (3, 12)
CLOUD_MIN_VALUE = 0.5
CLOUD_MIN_BLUE = -0.02
CLOUD_MAX_BLUE = 0.08
CLOUD_MIN_CONTRAST = 0.25


def cloud_above(img8: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Per column: whether the pixels just above ``rows`` (fractional, NaN = none) are white cloud
    (and sky) over darker ground: every pixel of rows 3-12 above bright and neutral or blue, some of
    them white, and brighter on average than rows 3-12 below by CLOUD_MIN_CONTRAST.

    A cumulus behind a ridge is unlike the clear sky an image's sky model is learnt on, yet it is no
    occluder: a rock, a person or a green hill in front of the skyline has dark or warm pixels
    (shadows, clothes, grass) among those rows, and far land seen through haze above a near hill is
    as blue as the sky's horizon, not white."""
    h, w = img8.shape[:2]
    # averaged over three columns (in 8 bits: the whole image blurred costs less than its floats),
    # and only the rows around the line read as floats
    smooth = cv2.blur(img8, (3, 1))
    cols = np.arange(w)
    r = np.round(np.nan_to_num(rows, nan=-10.0 * h)).astype(np.int64)
    offs = np.arange(CLOUD_ROWS[0], CLOUD_ROWS[1] + 1)
    up, dn = r[None, :] - offs[:, None], r[None, :] + offs[:, None]
    inside = (up.min(axis=0) >= 0) & (dn.max(axis=0) < h)
    px_up = smooth[np.clip(up, 0, h - 1), cols[None, :]].astype(np.float32) / np.float32(255.0)
    px_dn = smooth[np.clip(dn, 0, h - 1), cols[None, :]].astype(np.float32) / np.float32(255.0)
    v_up = px_up.max(axis=2)
    whitest = (px_up[..., 0] - px_up[..., 2]).min(axis=0)
    bright = (v_up.min(axis=0) >= CLOUD_MIN_VALUE) & (whitest >= CLOUD_MIN_BLUE) & (whitest <= CLOUD_MAX_BLUE)
    contrast = v_up.mean(axis=0) - px_dn.max(axis=2).mean(axis=0) >= CLOUD_MIN_CONTRAST
    return np.asarray(inside & bright & contrast)


def anchored(extra: np.ndarray, good: np.ndarray, links: np.ndarray, rows: np.ndarray, gap_px: int,
             max_step_px: float, wrap: bool) -> np.ndarray:
    """Per column: ``extra`` where it lies on a chain of ``extra`` or ``links`` columns (gaps of at
    most ``gap_px`` other columns) that meets a ``good`` column on both sides, within ``gap_px``
    columns of its ends and ``max_step_px`` rows of their rows.

    A ridge with a cloud behind it continues the line found under clear sky on either side, through
    columns with the cloud above them all along (``links``, whether or not their line is trusted);
    the edge of a shadow inside a rock near the camera, with bright rock face above it, is cut off
    from the line on either side by the rock's darker parts."""
    w = extra.size
    out = np.zeros(w, dtype=bool)
    if not good.any() or not extra.any():
        return out
    # a full circle is rotated to start at a good column: no chain then crosses the seam
    shift = int(np.argmax(good)) if wrap else 0
    ex, gd, ln, rw = (np.roll(a, -shift) for a in (extra & ~good, good, links, rows))
    idx = np.flatnonzero((ex | ln) & ~gd)
    if not idx.size:
        return out
    # chains: columns at most gap_px apart with no good column between them
    seen = np.cumsum(gd)
    cut = (np.diff(idx) > gap_px + 1) | (seen[idx[1:]] != seen[idx[:-1]])
    starts = np.r_[idx[0], idx[1:][cut]]
    ends = np.r_[idx[:-1][cut], idx[-1]]
    good_idx = np.flatnonzero(gd)
    for s, e in zip(starts, ends):
        k = np.searchsorted(good_idx, s)
        left = int(good_idx[k - 1]) if k > 0 else None
        right = int(good_idx[k]) if k < good_idx.size else (int(good_idx[0]) + w if wrap else None)
        if left is None or right is None or s - left > gap_px + 1 or right - e > gap_px + 1:
            continue
        if abs(rw[s] - rw[left]) > max_step_px or abs(rw[e] - rw[right % w]) > max_step_px:
            continue
        out[s : e + 1] = ex[s : e + 1]
    return np.roll(out, shift)
