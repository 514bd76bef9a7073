"""The skyline database as the estimator sees it: pure arrays over a grid of nodes.

:class:`SkylineGrid` holds each node's skyline as uint8 codes (with the node's offset and step),
the range of each horizon point when known, the ground's height and the terrain for exact renders.
The first pass of a search (``coarse.py``) reads the codes averaged over runs of COARSE_STRIDE
azimuths and the parallax variance of each run; a database makes both once, at its build
(:func:`first_pass_ahead`), or the grid makes them on first use.
"""

from __future__ import annotations

from dataclasses import KW_ONLY, dataclass
from functools import cached_property

import numpy as np

from appliance.estimator import parallax
from appliance.estimator.coarse_kernels import decimated
from appliance.estimator.raycast import Terrain

#: The first pass scores skylines averaged over runs of this many azimuths.
COARSE_STRIDE = 4


@dataclass(frozen=True)
class SkylineGrid:
    """What the estimator needs of a skyline database: uint8 codes with per-node offset and step,
    and the node grid's shape and ground spacing.  Pure arrays: no files, no projections."""

    codes: np.ndarray  # (n_nodes, n_az) uint8, 255 = no terrain
    offset_deg: np.ndarray  # (n_nodes,) float32, NaN = node on nodata
    step_deg: np.ndarray  # (n_nodes,) float32
    _: KW_ONLY
    n_rows: int
    n_cols: int
    dx_m: float
    dy_m: float
    #: (n_nodes, n_az) uint8 log-quantised range of each horizon point (255 = none); None = unknown
    distance_codes: np.ndarray | None = None
    ground_m: np.ndarray | None = None
    terrain: Terrain | None = None
    distance_min_m: float = 1.0
    distance_log_step: float = 0.05
    #: the first pass made ahead (at the database's build): :attr:`coarse`, and :meth:`coarse_tau2`
    #: with no map error; None = made on first use
    first_pass: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    @property
    def n_azimuths(self) -> int:
        return int(self.codes.shape[1])

    @property
    def has_parallax(self) -> bool:
        return self.distance_codes is not None

    @cached_property
    def rho2_m2(self) -> float:
        return parallax.offset_variance_m2(self.dx_m, self.dy_m)

    @cached_property
    def ground_gradient2(self) -> np.ndarray:
        """|grad z|^2 of the ground at every node, float32 (0 where unknown)."""
        ge, gn = self.ground_gradient
        return (ge * ge + gn * gn).astype(np.float32)

    @cached_property
    def ground_gradient(self) -> tuple[np.ndarray, np.ndarray]:
        if self.ground_m is None:
            zero = np.zeros(self.codes.shape[0])
            return zero, zero
        return parallax.ground_gradient(self.ground_m, self.n_rows, self.n_cols, self.dx_m, self.dy_m)

    def ground_gradient_at(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:attr:`ground_gradient` where only ``nodes`` are filled (0 elsewhere), for the kernels that
        read those nodes alone: the same values without the gradient of the whole map."""
        if self.ground_m is None or "ground_gradient" in self.__dict__:
            return self.ground_gradient
        return parallax.ground_gradient_at(self.ground_m, self.n_rows, self.n_cols, self.dx_m, self.dy_m, nodes)

    def ground_gradient2_at(self, nodes: np.ndarray,
                            gradient: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """:attr:`ground_gradient2` where only ``nodes`` are filled (0 elsewhere); ``gradient`` is
        :meth:`ground_gradient_at` of the same nodes when already made (not made twice)."""
        if self.ground_m is None or "ground_gradient2" in self.__dict__:
            return self.ground_gradient2
        ge, gn = self.ground_gradient_at(nodes) if gradient is None else gradient
        idx = np.asarray(nodes, dtype=np.int64).ravel()
        g2 = np.zeros(ge.size, dtype=np.float32)
        g2[idx] = (ge[idx] * ge[idx] + gn[idx] * gn[idx]).astype(np.float32)
        return g2

    @cached_property
    def convergence_deg(self) -> np.ndarray:
        if self.terrain is None:
            return np.zeros(self.codes.shape[0])
        return np.asarray(self.terrain.convergence_deg, dtype=np.float64)

    @cached_property
    def inverse_range2(self) -> np.ndarray:
        return parallax.inverse_range2_table(self.distance_min_m, self.distance_log_step)

    @cached_property
    def _coarse_tau2_cache(self) -> dict[float, np.ndarray]:
        return {}

    def coarse_tau2(self, map_sigma_m: float = 0.0) -> np.ndarray:
        """The model's variance (parallax, the map's height error) over each first-pass run of
        azimuths (uint8 codes); made once per map error."""
        assert self.distance_codes is not None
        cache = self._coarse_tau2_cache
        if map_sigma_m == 0.0 and self.first_pass is not None:
            return self.first_pass[2]
        if map_sigma_m not in cache:
            cache[map_sigma_m] = parallax.coarse_tau2_codes(
                self.codes, self.distance_codes, self.offset_deg, self.step_deg, self.ground_gradient2, self.rho2_m2,
                self.inverse_range2, COARSE_STRIDE, map_sigma_m)
        return cache[map_sigma_m]

    @cached_property
    def coarse(self) -> tuple[np.ndarray, np.ndarray]:
        """Codes averaged over runs of COARSE_STRIDE azimuths, and the nodes lacking terrain
        somewhere: made once, at the database's build or on first use, for every estimate on this grid."""
        if self.first_pass is not None:
            return self.first_pass[0], self.first_pass[1]
        return decimated(self.codes, self.offset_deg, COARSE_STRIDE)

    @property
    def az_step_deg(self) -> float:
        return 360.0 / self.n_azimuths

    def skylines_deg(self, index: np.ndarray | int) -> np.ndarray:
        codes = np.asarray(self.codes[index])
        off = np.asarray(self.offset_deg[index], dtype=np.float64)
        st = np.asarray(self.step_deg[index], dtype=np.float64)
        el = off[..., None] + st[..., None] * codes
        return np.where(codes == 255, np.nan, el)


def nearest_node(grid: SkylineGrid, row: float, col: float) -> int:
    """The node nearest fractional grid (row, col), clamped to the grid."""
    return (min(max(int(round(row)), 0), grid.n_rows - 1) * grid.n_cols
            + min(max(int(round(col)), 0), grid.n_cols - 1))


def first_pass_ahead(grid: SkylineGrid, codes: np.ndarray, distance_codes: np.ndarray,
                     nodes: slice) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The first pass made ahead (:attr:`SkylineGrid.first_pass`) for ``nodes`` of ``grid``, from
    their uint8 skyline and range codes (one row per node of the slice): the codes averaged over
    runs of COARSE_STRIDE azimuths, the nodes lacking terrain somewhere, and the parallax variance
    of each run with no map error (log codes).  ``grid`` gives the nodes' offsets and steps, the
    ground and the spacing; its own codes are not read, so a database being built can pass a grid
    of empty skylines and fill the first pass a block of nodes at a time."""
    offset, step = grid.offset_deg[nodes], grid.step_deg[nodes]
    coarse, partial = decimated(codes, offset, COARSE_STRIDE)
    tau2 = parallax.coarse_tau2_codes(codes, distance_codes, offset, step, grid.ground_gradient2[nodes], grid.rho2_m2,
                                      grid.inverse_range2, COARSE_STRIDE, 0.0)
    return coarse, partial, tau2
