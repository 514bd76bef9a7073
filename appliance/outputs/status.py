"""What an operator reads first on a report: the answer's status as a banner ("ok ± R m", or AMBIGUOUS
with the reasons the record's notes give) and where it is (latitude and longitude, UTM, MGRS and the
altitude), all read from the estimate's JSON record (:meth:`appliance.locating.position.Position.to_json`),
so that the page says what the record says.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from appliance.bodies import BodyName
from appliance.outputs.grid_refs import mgrs_ref, utm_ref

#: the reason given when the GPS truth, not the estimator, made the answer ambiguous
TRUTH_OUTSIDE = "the GPS truth lies outside the 95 % region"


@dataclass(frozen=True)
class StatusBanner:
    """The banner of one answer: ``ok`` (drawn green) or not (red), its headline ("ok ± 12.3 m" or
    "AMBIGUOUS") and, when ambiguous, the reasons."""

    ok: bool
    headline: str
    reasons: tuple[str, ...]


def status_banner(record: Mapping[str, Any]) -> StatusBanner:
    """The banner of an estimate's JSON record: "ok ± R m" (R the 95 % radius) when its status is ok,
    else "AMBIGUOUS" with its notes (their "ambiguous: " prefix dropped) and, where the GPS truth made it
    so, :data:`TRUTH_OUTSIDE`."""
    if record.get("status") == "ok":
        radius = record.get("radius95_m")
        return StatusBanner(True, "ok" if radius is None else f"ok ± {radius:.1f} m", ())
    reasons = [str(n).removeprefix("ambiguous: ") for n in record.get("notes") or []]
    if "truth" in record and not record.get("ambiguous", True):
        reasons.append(TRUTH_OUTSIDE)
    return StatusBanner(False, "AMBIGUOUS", tuple(reasons or ["no reason recorded"]))


def _hemispheres(lat: float, lon: float) -> str:
    return f"{abs(lat):.6f}° {'N' if lat >= 0 else 'S'}, {abs(lon):.6f}° {'E' if lon >= 0 else 'W'}"


def position_facts(record: Mapping[str, Any], body: str = BodyName.EARTH.value) -> list[tuple[str, str]]:
    """(name, value) rows of where the record's answer is: latitude and longitude, UTM and MGRS (on
    Earth, between 80 S and 84 N), and the camera's altitude (the map's vertical datum)."""
    lat, lon = float(record["lat"]), float(record["lon"])
    rows = [("latitude, longitude", f"{lat:.6f}, {lon:.6f} ({_hemispheres(lat, lon)})")]
    if body != BodyName.EARTH.value:
        rows.append(("UTM, MGRS", f"none on the {body.capitalize()}"))
    else:
        utm, mgrs = utm_ref(lat, lon), mgrs_ref(lat, lon)
        rows.append(("UTM (WGS 84)", "none beyond 80° S and 84° N" if utm is None else utm.text()))
        rows.append(("MGRS", "none beyond 80° S and 84° N" if mgrs is None else mgrs))
    alt = record.get("altitude_m")
    rows.append(("altitude", "off the map" if alt is None else f"{alt:.1f} m (the map's vertical datum)"))
    return rows
