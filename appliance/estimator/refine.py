"""Sub-cell refinement of the best candidate.

The paper's answer was a grid node, so its error could not fall below the grid's spacing.  Here the
skyline at a point between nodes is taken as the bilinear blend of the skylines of the nodes
around it, the measured skyline is shifted by fractions of an azimuth step (linear interpolation
on the circle), and the squared residual is minimised over position (+-1 cell around the best node,
in tenths of a cell) and heading (+-1 step, in tenths), all as small matrix products.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from appliance.estimator.estimate import SkylineGrid

FRACTIONS = np.linspace(-1.0, 1.0, 21)


def shift_circular(values: np.ndarray, shift_steps: np.ndarray) -> np.ndarray:
    """values[j + s] for fractional s, linear on the circle; NaN propagates.  Shape (len(s), n)."""
    n = values.size
    j = np.arange(n)[None, :] + np.asarray(shift_steps, float)[:, None]
    j0 = np.floor(j).astype(np.intp)
    t = j - j0
    return values[j0 % n] * (1 - t) + values[(j0 + 1) % n] * t


def refine_subcell(
    grid: SkylineGrid, measured: np.ndarray, node: int, heading_deg: float, rms_deg: float
) -> tuple[float, float, float, float]:
    """(row, col, heading_deg, rms_deg) of the continuous optimum near ``node``."""
    row, col = divmod(int(node), grid.n_cols)
    r0, r1 = max(row - 1, 0), min(row + 1, grid.n_rows - 1)
    c0, c1 = max(col - 1, 0), min(col + 1, grid.n_cols - 1)
    rr, cc = np.meshgrid(np.arange(r0, r1 + 1), np.arange(c0, c1 + 1), indexing="ij")
    sky = grid.skylines_deg((rr * grid.n_cols + cc).ravel()).reshape(rr.shape + (grid.n_azimuths,))
    if not np.isfinite(grid.offset_deg[(rr * grid.n_cols + cc).ravel()]).all():
        return float(row), float(col), heading_deg, rms_deg

    # positions on a fine lattice within the neighbourhood, bilinear blend of the node skylines
    fr = np.clip(row + FRACTIONS, r0, r1)
    fc = np.clip(col + FRACTIONS, c0, c1)
    grid_r, grid_c = np.meshgrid(fr, fc, indexing="ij")
    PR, PC = grid_r.ravel(), grid_c.ravel()
    i0 = np.minimum(np.floor(PR - r0).astype(int), max(r1 - r0 - 1, 0))
    j0 = np.minimum(np.floor(PC - c0).astype(int), max(c1 - c0 - 1, 0))
    i1 = np.minimum(i0 + 1, r1 - r0)
    j1 = np.minimum(j0 + 1, c1 - c0)
    ti = (PR - r0 - i0)[:, None]
    tj = (PC - c0 - j0)[:, None]
    S = (sky[i0, j0] * (1 - ti) * (1 - tj) + sky[i0, j1] * (1 - ti) * tj
         + sky[i1, j0] * ti * (1 - tj) + sky[i1, j1] * ti * tj)  # (P, A)

    # the measured skyline as it would read at each trial heading: true az = input az + heading
    step = grid.az_step_deg
    trial = heading_deg + FRACTIONS * step
    M = shift_circular(measured, -trial / step)  # (H, A): M[h, j] = measured at true az j
    W = np.isfinite(M)
    ok_s = np.isfinite(S).all(axis=0)
    W &= ok_s[None, :]
    M0 = np.where(W, M, 0.0)
    S0 = np.where(ok_s[None, :], S, 0.0)
    Wf = W.astype(float)
    n = Wf.sum(axis=1)
    ssd = (np.sum(Wf * M0 * M0, axis=1)[:, None] - 2.0 * (M0 * Wf) @ S0.T + Wf @ (S0 * S0).T)
    ssd = np.maximum(ssd, 0.0) / np.maximum(n, 1.0)[:, None]  # mean square, comparable across headings
    h, p = np.unravel_index(int(np.argmin(ssd)), ssd.shape)
    return float(PR[p]), float(PC[p]), float(trial[h]), math.sqrt(float(ssd[h, p]))
