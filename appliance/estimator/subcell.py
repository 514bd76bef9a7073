"""Sub-cell refinement between the database's skylines, for a grid without terrain.

With terrain the answer is refined on exact renders (``exact.py``); without, ``refinement.py`` falls
back to this.

The paper's answer was a grid node, so its error could not fall below the grid's spacing.  Here the
skyline at a point between nodes is taken as the bilinear blend of the skylines of the nodes
around it, turned by fractions of an azimuth step (linear interpolation on the circle), and the
mean squared residual is minimised over position (+-1 cell around the node)
and heading (+-1 step): quarters first, then twentieths around the best quarter.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from appliance.estimator.skyline_grid import SkylineGrid

#: A first lattice of quarter cells and quarter steps over +-1, then twentieths over +-1/5.
COARSE = np.linspace(-1.0, 1.0, 9)
FINE = np.linspace(-0.2, 0.2, 9)


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

    pr, pc, h, _ = _search(grid, measured, sky, (r0, r1, c0, c1), row, col, heading_deg, COARSE, COARSE)
    return _search(grid, measured, sky, (r0, r1, c0, c1), pr, pc, h, FINE, FINE)


def _search(
    grid: SkylineGrid, measured: np.ndarray, sky: np.ndarray, box: tuple[int, int, int, int],
    row: float, col: float, heading_deg: float, pos_fractions: np.ndarray, head_fractions: np.ndarray,
) -> tuple[float, float, float, float]:
    r0, r1, c0, c1 = box
    # positions on a fine lattice within the neighbourhood, bilinear blend of the node skylines
    fr = np.clip(row + pos_fractions, r0, r1)
    fc = np.clip(col + pos_fractions, c0, c1)
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

    # The model is shifted, not the measurement: interpolating the noisy measurement between
    # samples would average its noise away at fractional shifts and bias the heading towards them.
    step = grid.az_step_deg
    trial = heading_deg + head_fractions * step
    ok_s = np.isfinite(S).all(axis=0)
    S0 = np.where(ok_s[None, :], S, 0.0)
    valid = np.isfinite(measured)
    m0 = np.where(valid, measured, 0.0)
    ssd = np.empty((trial.size, S.shape[0]))
    n_valid = max(float(valid.sum()), 1.0)
    for ih, phi in enumerate(trial):
        # model value at true azimuth j + phi, i.e. at input azimuth j: a whole turn and a fraction
        whole = int(np.floor(phi / step))
        t = phi / step - whole
        a = np.roll(S0, -whole, axis=1)
        b = np.roll(S0, -whole - 1, axis=1)
        ok = valid & np.roll(ok_s, -whole) & np.roll(ok_s, -whole - 1)
        resid = m0[None, :] - (a * (1.0 - t) + b * t)
        ssd[ih] = np.einsum("pj,pj,j->p", resid, resid, ok.astype(float)) / (n_valid if ok.all() else
                                                                             max(float(ok.sum()), 1.0))
    best_h, best_p = (int(v) for v in np.unravel_index(int(np.argmin(ssd)), ssd.shape))
    return float(PR[best_p]), float(PC[best_p]), float(trial[best_h]), math.sqrt(max(float(ssd[best_h, best_p]), 0.0))
