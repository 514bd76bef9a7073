"""Grid search: squared residuals between one measured skyline and every database skyline.

For a candidate node and a heading correction of k azimuth steps, the residual sum is

    SSD(node, k) = sum_j w_j (m_j - s_node[j + k])^2,

m on the database's azimuth grid (w = 0 where m is missing).  With a compass k spans a few steps
around zero: a compiled loop over nodes (numba, both cores) decodes each node's uint8 skyline
once and scores every shift on contiguous memory.  With no compass all shifts are scored at once
as a circular cross-correlation by FFT:

    SSD(k) = sum w m^2 - 2 (wm * s)(k) + (w * s^2)(k).

A database azimuth with no terrain (code 255) at a node is left out of that node's sum and the
sum rescaled to the measured count; a node missing more than a tenth of them is not a candidate.
"""

from __future__ import annotations

import math

import numba
import numpy as np

MISSING_CODE = 255
MAX_MISSING_FRACTION = 0.1
BLOCK = 256


@numba.njit(cache=True, parallel=True, fastmath=True)
def _ssd_shifts(
    codes: np.ndarray,
    offset: np.ndarray,
    step: np.ndarray,
    m: np.ndarray,
    w: np.ndarray,
    rows: np.ndarray,
    shifts: np.ndarray,
    stride: int,
    out: np.ndarray,
) -> None:
    """out[r, k] = SSD of node rows[r] at shift shifts[r, k], over every ``stride``-th azimuth."""
    n_az = codes.shape[1]
    n_shift = shifts.shape[1]
    n_meas = 0.0
    for j in range(0, n_az, stride):
        n_meas += w[j]
    n_rows = rows.size
    n_blocks = (n_rows + BLOCK - 1) // BLOCK
    for b in numba.prange(n_blocks):
        buf = np.empty(2 * n_az, dtype=np.float32)
        for r in range(b * BLOCK, min(n_rows, (b + 1) * BLOCK)):
            i = rows[r]
            o = offset[i]
            if math.isnan(o):
                for k in range(n_shift):
                    out[r, k] = np.inf
                continue
            st = step[i]
            missing = 0
            for j in range(n_az):
                c = codes[i, j]
                if c == MISSING_CODE:
                    missing += 1
                v = np.float32(o + st * c)
                buf[j] = v
                buf[j + n_az] = v
            for k in range(n_shift):
                sh = shifts[r, k] % n_az
                acc = np.float32(0.0)
                if missing == 0:
                    for j in range(0, n_az, stride):
                        d = m[j] - buf[sh + j]
                        acc += w[j] * d * d
                    out[r, k] = acc
                else:
                    cnt = 0.0
                    for j in range(0, n_az, stride):
                        if w[j] > 0 and codes[i, (sh + j) % n_az] != MISSING_CODE:
                            d = m[j] - buf[sh + j]
                            acc += w[j] * d * d
                            cnt += w[j]
                    if cnt < (1.0 - MAX_MISSING_FRACTION) * n_meas:
                        out[r, k] = np.inf
                    else:
                        out[r, k] = acc * n_meas / cnt


def ssd_for_shifts(
    codes: np.ndarray,
    offset_deg: np.ndarray,
    step_deg: np.ndarray,
    measured_deg: np.ndarray,
    shifts: np.ndarray,
    rows: np.ndarray | None = None,
    stride: int = 1,
) -> np.ndarray:
    """SSD (deg^2) of nodes ``rows`` (default all) for each shift (azimuth steps).

    ``shifts`` is 1-D (the same for every node) or (len(rows), k) per node.  ``measured_deg`` is on
    the database's azimuth grid with NaN where missing.  With ``stride`` > 1 only every stride-th
    azimuth is used and the sum is scaled to the full count: a cheap first pass.  inf marks nodes
    that cannot be candidates (nodata, or too many azimuths without terrain).
    """
    valid = np.isfinite(measured_deg)
    m = np.where(valid, measured_deg, 0.0).astype(np.float32)
    w = valid.astype(np.float32)
    idx = np.arange(codes.shape[0], dtype=np.int64) if rows is None else np.asarray(rows, dtype=np.int64)
    sh = np.asarray(shifts, dtype=np.int64)
    if sh.ndim == 1:
        sh = np.broadcast_to(sh, (idx.size, sh.size))
    sh = np.ascontiguousarray(sh)
    out = np.empty((idx.size, sh.shape[1]), dtype=np.float32)
    _ssd_shifts(codes, offset_deg, step_deg, m, w, idx, sh, int(stride), out)
    if stride > 1:
        n_full = float(w.sum())
        n_coarse = float(w[::stride].sum())
        out *= n_full / max(n_coarse, 1.0)
    return out


def ssd_all_shifts(
    codes: np.ndarray,
    offset_deg: np.ndarray,
    step_deg: np.ndarray,
    measured_deg: np.ndarray,
    chunk: int = 16384,
):
    """Yield (start, SSD block of shape (rows, n_az)) for every shift by FFT, in node chunks.

    Block column k is the shift of k azimuth steps.  Nodes on nodata, or missing more than a
    tenth of the measured azimuths, are inf.
    """
    import scipy.fft

    n_nodes, n_az = codes.shape
    valid = np.isfinite(measured_deg)
    w = valid.astype(np.float64)
    wm = np.where(valid, measured_deg, 0.0)
    n_meas = w.sum()
    const = float(np.sum(wm * wm))
    f_wm = np.conj(scipy.fft.rfft(wm))
    f_w = np.conj(scipy.fft.rfft(w))
    for start in range(0, n_nodes, chunk):
        c = np.asarray(codes[start : start + chunk])
        off = np.asarray(offset_deg[start : start + chunk], dtype=np.float64)
        st = np.asarray(step_deg[start : start + chunk], dtype=np.float64)
        miss = c == MISSING_CODE
        s = off[:, None] + st[:, None] * c
        s[miss] = 0.0
        present = (~miss).astype(np.float64)
        # cross-correlations over the circle: corr(k) = sum_j a_j b_{j+k}
        fs = scipy.fft.rfft(np.stack([s, s * s, present]), axis=-1, workers=2)
        cross = scipy.fft.irfft(fs[0] * f_wm, n=n_az, axis=-1, workers=2)
        sq = scipy.fft.irfft(fs[1] * f_w, n=n_az, axis=-1, workers=2)
        cnt = scipy.fft.irfft(fs[2] * f_w, n=n_az, axis=-1, workers=2)
        cnt = np.rint(cnt)
        if miss.any():
            # the measured sum of squares only over azimuths where the node has terrain
            const_k = scipy.fft.irfft(scipy.fft.rfft(present, axis=-1) * np.conj(scipy.fft.rfft(wm * wm)),
                                      n=n_az, axis=-1)
        else:
            const_k = const
        ssd = np.maximum(const_k - 2.0 * cross + sq, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            ssd = np.where(cnt >= (1.0 - MAX_MISSING_FRACTION) * n_meas, ssd * n_meas / np.maximum(cnt, 1), np.inf)
        ssd[~np.isfinite(off)] = np.inf
        yield start, ssd
