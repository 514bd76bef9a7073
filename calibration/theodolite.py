"""The estimator's sigma interval from a theodolite survey (paper section 5.2).

n points are sighted twice: once through the camera platform (the elevation angle the vision chain
measures) and once with a theodolite (the reference).  The residuals camera - theodolite have a
sample standard deviation s (n - 1 degrees of freedom); with residuals normal of standard deviation
sigma, (n - 1) s^2 / sigma^2 is chi-square with n - 1 degrees of freedom, so the two-sided confidence
interval for sigma at level c = 1 - alpha is

    [ sqrt((n-1) s^2 / chi2_{1-alpha/2}),  sqrt((n-1) s^2 / chi2_{alpha/2}) ]

where chi2_q is the q-quantile.  This is the sensor's share: the camera against a perfect reference.
The estimator learns the skyline's noise from each skyline's own residuals (the map's share, the
stitch, a residual tilt: whatever a fit leaves); the sensor's interval is its floor, since no skyline
is read more finely than the sensor reads it.  A map known to add error of its own may add a share
(``--map-share``, none by default), combined with the sensor's in quadrature, bound by bound:

    floor = [ sqrt(lo_sensor^2 + lo_map^2),  sqrt(hi_sensor^2 + hi_map^2) ]

``viper calibrate theodolite --config`` writes it as ``[estimator] sensor_sigma_deg``; the search's
``sigma_deg`` is left as it is.
All angles are elevations in degrees above the local horizontal.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.stats import chi2
from viper_calibration.csvtable import read_input, read_rows

from appliance.errors import CalibrationError, InputError

HEADER = ("point", "camera_elevation_deg", "theodolite_elevation_deg")
MIN_POINTS = 3
#: The map's and model's share of the estimator's sigma (deg, [lo, hi]), combined with the sensor's.
MAP_SIGMA_DEG = (0.0, 0.0)
ARCSEC_PER_DEG = 3600.0


@dataclass(frozen=True)
class ElevationPoint:
    """One surveyed point: the camera's and the theodolite's elevation of it (degrees)."""

    point: str
    camera_elevation_deg: float
    theodolite_elevation_deg: float

    @property
    def residual_deg(self) -> float:
        """Camera minus theodolite elevation, degrees."""
        return self.camera_elevation_deg - self.theodolite_elevation_deg


@dataclass(frozen=True)
class SigmaCalibration:
    """The result: residual statistics, the confidence interval for the sensor's sigma (degrees) and the
    floor of the estimator's learned sigma (the sensor's and an optional map share in quadrature)."""

    points: tuple[ElevationPoint, ...]
    confidence: float
    mean_residual_deg: float
    s_deg: float
    sigma_deg: tuple[float, float]  # the sensor's share, from the survey
    map_sigma_deg: tuple[float, float] = MAP_SIGMA_DEG

    @property
    def estimator_sigma_deg(self) -> tuple[float, float]:
        """The floor of the sigma the estimator learns: sensor and map shares in quadrature, bound by bound."""
        return combine_sigma(self.sigma_deg, self.map_sigma_deg)

    @property
    def n(self) -> int:
        return len(self.points)

    @property
    def residuals_deg(self) -> tuple[float, ...]:
        return tuple(p.residual_deg for p in self.points)


def parse_points_csv(data: bytes, source: str = "<points>") -> tuple[ElevationPoint, ...]:
    """Parse the survey CSV (header ``point,camera_elevation_deg,theodolite_elevation_deg``)."""
    rows = read_rows(data, source, HEADER)
    points: list[ElevationPoint] = []
    seen: set[str] = set()
    for line_no, row in enumerate(rows, start=2):
        if len(row) != len(HEADER):
            raise InputError(f"{source}:{line_no}: expected {len(HEADER)} fields, got {len(row)}")
        name = row[0].strip()
        if not name:
            raise InputError(f"{source}:{line_no}: empty point name")
        if name in seen:
            raise InputError(f"{source}:{line_no}: point {name!r} appears twice")
        seen.add(name)
        values = []
        for column, cell in zip(HEADER[1:], row[1:], strict=True):
            try:
                value = float(cell)
            except ValueError:
                raise InputError(f"{source}:{line_no}: {column} {cell.strip()!r} is not a number") from None
            if not math.isfinite(value) or abs(value) > 90.0:
                raise InputError(
                    f"{source}:{line_no}: {column} {cell.strip()} is not an elevation in [-90, 90]"
                )
            values.append(value)
        points.append(ElevationPoint(name, values[0], values[1]))
    return tuple(points)


def read_points_csv(path: str | Path) -> tuple[ElevationPoint, ...]:
    return parse_points_csv(read_input(path), source=str(path))


def sigma_interval(s: float, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided chi-square confidence interval for sigma from a sample deviation s of n residuals."""
    if not 0.0 < confidence < 1.0:
        raise InputError(f"confidence must lie strictly between 0 and 1, got {confidence}")
    if n < 2:
        raise CalibrationError(f"a sigma interval needs at least 2 residuals, got {n}")
    dof = n - 1
    alpha = 1.0 - confidence
    upper_q = float(chi2.ppf(1.0 - alpha / 2.0, dof))
    lower_q = float(chi2.ppf(alpha / 2.0, dof))
    return math.sqrt(dof * s * s / upper_q), math.sqrt(dof * s * s / lower_q)


def combine_sigma(sensor_deg: tuple[float, float], map_deg: tuple[float, float]) -> tuple[float, float]:
    """Independent shares of one interval added in quadrature, lower bound with lower bound."""
    return math.hypot(sensor_deg[0], map_deg[0]), math.hypot(sensor_deg[1], map_deg[1])


def check_map_sigma(map_deg: tuple[float, float]) -> tuple[float, float]:
    lo, hi = map_deg
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo <= hi):
        raise InputError(f"map share {lo},{hi} deg: expected 0 <= lo <= hi")
    return float(lo), float(hi)


def calibrate_sigma(
    points: Sequence[ElevationPoint], confidence: float = 0.95, map_sigma_deg: tuple[float, float] = MAP_SIGMA_DEG
) -> SigmaCalibration:
    """Residual statistics and the sigma interval; refuses degenerate surveys with one clear line."""
    n = len(points)
    if n < MIN_POINTS:
        raise CalibrationError(f"{n} surveyed point(s); the sigma interval needs at least {MIN_POINTS}")
    camera = np.array([p.camera_elevation_deg for p in points])
    theodolite = np.array([p.theodolite_elevation_deg for p in points])
    for name, column in (("camera_elevation_deg", camera), ("theodolite_elevation_deg", theodolite)):
        if np.ptp(column) == 0.0:
            raise CalibrationError(
                f"{name} is constant ({column[0]} deg) over all {n} points; survey several elevations"
            )
    residuals = camera - theodolite
    s = float(np.std(residuals, ddof=1))
    if s == 0.0:
        raise CalibrationError(
            f"all {n} residuals are equal ({residuals[0]} deg); a zero spread gives no sigma interval"
        )
    return SigmaCalibration(
        points=tuple(points),
        confidence=confidence,
        mean_residual_deg=float(np.mean(residuals)),
        s_deg=s,
        sigma_deg=sigma_interval(s, n, confidence),
        map_sigma_deg=check_map_sigma(map_sigma_deg),
    )


def format_report(result: SigmaCalibration) -> str:
    """The residual table and the interval, as printed by ``viper calibrate theodolite``."""
    width = max(5, *(len(p.point) for p in result.points))
    lines = [
        f"{'point':<{width}}  {'camera_deg':>11}  {'theodolite_deg':>14}"
        f"  {'residual_deg':>12}  {'residual_arcsec':>15}",
    ]
    for p in result.points:
        lines.append(
            f"{p.point:<{width}}  {p.camera_elevation_deg:>11.5f}  {p.theodolite_elevation_deg:>14.5f}"
            f"  {p.residual_deg:>12.6f}  {p.residual_deg * ARCSEC_PER_DEG:>15.2f}"
        )
    lo, hi = result.sigma_deg
    lines += [
        f"n = {result.n}, mean residual = {result.mean_residual_deg:.6f} deg"
        f" ({result.mean_residual_deg * ARCSEC_PER_DEG:.2f} arcsec)",
        f"s = {result.s_deg:.6f} deg ({result.s_deg * ARCSEC_PER_DEG:.2f} arcsec),"
        f" {result.n - 1} degrees of freedom",
        f"{result.confidence * 100:g}% interval for sigma: [{lo:.6f}, {hi:.6f}] deg"
        f" ([{lo * ARCSEC_PER_DEG:.2f}, {hi * ARCSEC_PER_DEG:.2f}] arcsec): the sensor's share",
        f"map's share: [{result.map_sigma_deg[0]:g}, {result.map_sigma_deg[1]:g}] deg",
        "floor of the estimator's learned sigma (sensor and map in quadrature): "
        f"[{result.estimator_sigma_deg[0]:.6f}, {result.estimator_sigma_deg[1]:.6f}] deg",
    ]
    return "\n".join(lines)
