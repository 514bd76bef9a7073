"""Quantisation of skylines and horizon ranges into the database's one-byte codes.

Elevation (deg) = offset + step * code.  The step is 0.1 degree (quantisation error at most 0.05
degree) unless a node's skyline spans more than 25.4 degrees, where it grows to span/254.  Range
(m) = DISTANCE_MIN_M * exp(DISTANCE_LOG_STEP * code): 5 % steps from 1 m to 300 km.  Code 255
(MISSING_CODE) means no terrain along that azimuth.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from appliance.numerics import FAST_FINITE

DISTANCE_MIN_M = 1.0
DISTANCE_LOG_STEP = 0.05
MISSING_CODE = 255
BASE_STEP_DEG = 0.1
MAX_SPAN_DEG = 25.0
MISSING_CDEG = np.iinfo(np.int16).min  # no terrain, in the build's int16 centidegrees


def encode_distance(distance_m: np.ndarray) -> np.ndarray:
    """uint8 log-quantised ranges (255 where NaN)."""
    d = np.asarray(distance_m, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.rint(np.log(np.maximum(d, DISTANCE_MIN_M) / DISTANCE_MIN_M) / DISTANCE_LOG_STEP)
    return np.where(np.isfinite(d), np.clip(c, 0, MISSING_CODE - 1), MISSING_CODE).astype(np.uint8)


def decode_distance(codes: np.ndarray) -> np.ndarray:
    c = np.asarray(codes)
    return np.where(c == MISSING_CODE, np.nan, DISTANCE_MIN_M * np.exp(DISTANCE_LOG_STEP * c.astype(np.float64)))


@numba.njit(cache=True, inline="always")
def _atan(x: float) -> float:
    """Arctangent to 1e-5 rad (0.0006 deg), branch-light so that loops over it vectorise."""
    ax = abs(x)
    inv = ax > 1.0
    t = 1.0 / ax if inv else ax
    t2 = t * t
    # minimax polynomial for atan(t), 0 <= t <= 1
    p = t * (0.99997726 + t2 * (-0.33262347 + t2 * (0.19354346 + t2 * (-0.11643287 + t2 * (0.05265332
                                                                                         + t2 * -0.01172120)))))
    r = 0.5 * math.pi - p if inv else p
    return -r if x < 0 else r


@numba.njit(cache=True, nogil=True, fastmath=FAST_FINITE)
def store_centidegrees(tan: np.ndarray, far: np.ndarray, out: np.ndarray, dist: np.ndarray) -> None:
    """One azimuth of every node (row-major over the window): out[node] = elevation in hundredths
    of a degree (int16; MISSING_CDEG where NaN); dist[node] = the horizon's log-quantised range."""
    rows, cols = tan.shape
    scale = 100.0 * 180.0 / math.pi
    inv_log = 1.0 / DISTANCE_LOG_STEP
    for r in range(rows):
        line = tan[r]
        fline = far[r]
        base = r * cols
        for c in range(cols):
            t = line[c]
            if t != t:
                out[base + c] = MISSING_CDEG
                dist[base + c] = MISSING_CODE
            else:
                out[base + c] = np.int16(round(_atan(t) * scale))
                f = fline[c]
                if f != f:
                    dist[base + c] = MISSING_CODE
                else:
                    code = round(math.log(max(f, DISTANCE_MIN_M) / DISTANCE_MIN_M) * inv_log)
                    dist[base + c] = min(max(code, 0), MISSING_CODE - 1)


@numba.njit(cache=True)
def _quantize_row(row: np.ndarray, codes: np.ndarray, offs: np.ndarray, steps: np.ndarray, i: int) -> None:
    """Offset, step and uint8 codes of one skyline (deg, NaN = missing) into row i."""
    lo = np.inf
    hi = -np.inf
    for e in row:
        if not math.isnan(e):
            lo = min(lo, e)
            hi = max(hi, e)
    if lo > hi:
        offs[i] = np.nan
        steps[i] = BASE_STEP_DEG
        codes[i, :] = MISSING_CODE
        return
    o = np.float32(lo)
    st = np.float32(max(BASE_STEP_DEG, (hi - lo) / (MISSING_CODE - 1)))
    offs[i] = o
    steps[i] = st
    for j in range(row.size):
        e = row[j]
        if math.isnan(e):
            codes[i, j] = MISSING_CODE
        else:
            codes[i, j] = min(max(round((e - o) / st), 0), MISSING_CODE - 1)


@numba.njit(cache=True, nogil=True)
def turn_and_quantize(cdeg: np.ndarray, dgrid: np.ndarray, shift: np.ndarray, codes: np.ndarray,
                       dist: np.ndarray, offs: np.ndarray, steps: np.ndarray, lo: int, hi: int) -> None:
    """Nodes lo..hi-1: resample each node's skyline (cdeg[azimuth, node], azimuth-major) from grid
    to true azimuths (true = grid + shift steps, linear on the circle; ranges from the nearer
    azimuth), then quantise it into codes[node]."""
    n_az = cdeg.shape[0]
    block = 256
    src = np.empty((block, n_az), dtype=np.int16)
    dsrc = np.empty((block, n_az), dtype=np.uint8)
    row = np.empty(n_az)
    for b0 in range(lo, hi, block):
        b1 = min(b0 + block, hi)
        for j in range(n_az):  # a block of nodes gathered azimuth by azimuth: contiguous reads
            for i in range(b0, b1):
                src[i - b0, j] = cdeg[j, i]
                dsrc[i - b0, j] = dgrid[j, i]
        for i in range(b0, b1):
            s = src[i - b0]
            ds = dsrc[i - b0]
            sh = shift[i]
            whole = int(math.floor(sh))
            w = sh - whole
            if w == 0.0 and whole == 0:
                for j in range(n_az):
                    c = s[j]
                    row[j] = np.nan if c == MISSING_CDEG else c / 100.0
                    dist[i, j] = ds[j]
            else:
                # value at grid azimuth j - shift: between j - whole - 1 (weight w) and j - whole (1 - w)
                for j in range(n_az):
                    i1 = (j - whole) % n_az
                    i0 = (i1 - 1) % n_az
                    a = s[i0]
                    bb = s[i1]
                    if a == MISSING_CDEG or bb == MISSING_CDEG:
                        row[j] = np.nan
                        dist[i, j] = MISSING_CODE
                    else:
                        row[j] = (a * w + bb * (1.0 - w)) / 100.0
                        dist[i, j] = ds[i0] if w >= 0.5 else ds[i1]
            _quantize_row(row, codes, offs, steps, i)


@numba.njit(cache=True, parallel=True)
def _quantize_rows(elev: np.ndarray, codes: np.ndarray, offs: np.ndarray, steps: np.ndarray) -> None:
    for i in numba.prange(elev.shape[0]):
        _quantize_row(elev[i], codes, offs, steps, i)


def quantize(elev_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-node offset and step, and uint8 codes, of skylines ``elev_deg[n, n_az]`` (NaN = missing).

    The step is 0.1 degree (error at most 0.05) unless the skyline spans more than 25.4 degrees."""
    e = np.ascontiguousarray(elev_deg, dtype=np.float64)
    codes = np.empty(e.shape, dtype=np.uint8)
    offs = np.empty(e.shape[0], dtype=np.float32)
    steps = np.empty(e.shape[0], dtype=np.float32)
    _quantize_rows(e, codes, offs, steps)
    return codes, offs, steps
