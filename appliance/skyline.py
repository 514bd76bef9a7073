"""The skyline record and its CSV form, shared by the renderer, the vision chain and the estimator.

CSV: header ``azimuth_deg,elevation_deg``; one row per azimuth (degrees clockwise from north, as
the heading sensor reports it); an empty elevation means missing (masked, occluded, not detected).
A UTF-8 byte order mark (a spreadsheet's export) is skipped; an azimuth given twice (360 is 0) is
merged when both rows agree and refused when they do not.  A file is read only if it is a regular
file of at most 32 MiB and 360,000 rows (:mod:`appliance.inputs`).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from appliance.atomic import write_text_atomic
from appliance.errors import InputError
from appliance.inputs import MAX_SKYLINE_BYTES, MAX_SKYLINE_ROWS, read_text_bounded

HEADER = ("azimuth_deg", "elevation_deg")
#: The optional third column: the detector's confidence in each azimuth (0..1), a weight in the likelihood.
HEADER_WITH_CONFIDENCE = ("azimuth_deg", "elevation_deg", "confidence")


@dataclass(frozen=True)
class Skyline:
    """Elevation of the skyline (degrees above the local horizontal) per azimuth; NaN = missing.
    ``confidence`` (0..1 per azimuth, optional) says how much the detector trusts each one."""

    azimuth_deg: np.ndarray
    elevation_deg: np.ndarray
    confidence: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.azimuth_deg.shape != self.elevation_deg.shape or self.azimuth_deg.ndim != 1:
            raise InputError("skyline: azimuth and elevation must be 1-D arrays of the same length")
        c = self.confidence
        if c is not None:
            if c.shape != self.azimuth_deg.shape:
                raise InputError("skyline: one confidence per azimuth")
            ok = np.isfinite(self.elevation_deg)
            if not np.all((c[ok] >= 0.0) & (c[ok] <= 1.0)):
                raise InputError("skyline: confidence outside [0, 1]")

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.elevation_deg)

    @property
    def valid_fraction(self) -> float:
        return float(self.valid.mean()) if self.valid.size else 0.0


def read_skyline_csv(path: str | Path) -> Skyline:
    """Read a skyline CSV; malformed content raises :class:`InputError` naming the file and line."""
    p = Path(path)
    try:
        text = read_text_bounded(p, MAX_SKYLINE_BYTES, "skyline file", encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError(f"{p}: skyline file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot read skyline: {exc}") from None
    return parse_skyline_csv(text, name=str(p))


def parse_skyline_csv(text: str, name: str = "<skyline>") -> Skyline:
    text = text.removeprefix("\ufeff")
    rows: list[list[str]] = []
    try:
        for r in csv.reader(io.StringIO(text)):
            if any(c.strip() for c in r):
                rows.append(r)
                if len(rows) > MAX_SKYLINE_ROWS + 1:
                    raise InputError(f"{name}: more than {MAX_SKYLINE_ROWS:,} rows (a skyline has one per azimuth)")
    except csv.Error as exc:
        raise InputError(f"{name}: not a CSV file: {exc}") from None
    if not rows:
        raise InputError(f"{name}: empty skyline file")
    header = tuple(c.strip() for c in rows[0])
    if header not in (HEADER, HEADER_WITH_CONFIDENCE):
        raise InputError(f"{name}: expected header 'azimuth_deg,elevation_deg[,confidence]', "
                         f"got {','.join(header)!r}")
    if len(rows) < 2:
        raise InputError(f"{name}: no skyline rows after the header")
    fields = len(header)
    az = np.empty(len(rows) - 1)
    el = np.empty(len(rows) - 1)
    conf = np.ones(len(rows) - 1)
    for i, row in enumerate(rows[1:]):
        line = i + 2
        if len(row) != fields:
            raise InputError(f"{name}: line {line}: expected {fields} fields, got {len(row)}")
        if fields == 3 and row[2].strip() not in ("", "nan"):
            try:
                conf[i] = float(row[2])
            except ValueError:
                raise InputError(f"{name}: line {line}: confidence {row[2]!r} is not a number") from None
            if not 0.0 <= conf[i] <= 1.0:
                raise InputError(f"{name}: line {line}: confidence {conf[i]} outside [0, 1]")
        try:
            az[i] = float(row[0])
        except ValueError:
            raise InputError(f"{name}: line {line}: azimuth {row[0]!r} is not a number") from None
        cell = row[1].strip()
        if cell == "" or cell.lower() == "nan":
            el[i] = math.nan
            continue
        try:
            el[i] = float(cell)
        except ValueError:
            raise InputError(f"{name}: line {line}: elevation {cell!r} is not a number") from None
        if not -90.0 <= el[i] <= 90.0:
            raise InputError(f"{name}: line {line}: elevation {el[i]} outside [-90, 90] degrees")
    if not np.all(np.isfinite(az)):
        raise InputError(f"{name}: azimuths must be finite")
    az = np.mod(az, 360.0)
    keep = _merge_duplicates(az, el, conf, name)
    return Skyline(az[keep], el[keep], conf[keep] if fields == 3 else None)


def _merge_duplicates(az: np.ndarray, el: np.ndarray, conf: np.ndarray, name: str) -> np.ndarray:
    """Indices of the rows to keep: the first of each azimuth; a repeat must agree with it."""
    first: dict[float, int] = {}
    keep: list[int] = []
    for i, a in enumerate(az.tolist()):
        j = first.setdefault(a, i)
        if j == i:
            keep.append(i)
            continue
        same_el = (math.isnan(el[i]) and math.isnan(el[j])) or el[i] == el[j]
        if not (same_el and conf[i] == conf[j]):
            raise InputError(
                f"{name}: line {i + 2}: azimuth {a:g} deg already on line {j + 2} with another value "
                f"(elevation {_fmt(el[j])} vs {_fmt(el[i])}, confidence {conf[j]:g} vs {conf[i]:g})"
            )
    return np.asarray(keep, dtype=np.intp)


def _fmt(v: float) -> str:
    return "missing" if math.isnan(v) else f"{v:g}"


def format_skyline_csv(skyline: Skyline, decimals: int = 4) -> str:
    out = io.StringIO()
    conf = skyline.confidence
    out.write(",".join(HEADER if conf is None else HEADER_WITH_CONFIDENCE) + "\n")
    for i, (a, e) in enumerate(zip(skyline.azimuth_deg, skyline.elevation_deg)):
        el = "" if not math.isfinite(e) else f"{e:.{decimals}f}"
        if conf is None:
            out.write(f"{a:g},{el}\n")
        else:
            out.write(f"{a:g},{el},{'' if not el else f'{conf[i]:.3f}'}\n")
    return out.getvalue()


def write_skyline_csv(skyline: Skyline, path: str | Path) -> None:
    """Write atomically (:func:`appliance.atomic.write_text_atomic`)."""
    write_text_atomic(path, format_skyline_csv(skyline))
