"""A place on Earth as a field team writes it: UTM (zone, hemisphere, easting and northing on WGS84, by
pyproj) and the MGRS grid reference made from it (:func:`utm_ref`, :func:`mgrs_ref`).

UTM covers 80 degrees south to 84 degrees north, with the zones' exceptions around Norway and Svalbard;
beyond it (the polar caps, UPS) both return None.  MGRS here is the 100 km square lettering of WGS84
(the "AA" scheme: columns A-H, J-R, S-Z by zone, rows A-V restarting every 2,000 km, shifted by five
letters in even zones), at 1 m, the digits truncated (after rounding to the millimetre) as MGRS reads
them.  Other bodies have no UTM.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

from pyproj import Transformer

#: latitude bands of 8 degrees from 80 S (X spans 72-84 N)
_BANDS = "CDEFGHJKLMNPQRSTUVWX"
#: the 100 km column letters of zones 1, 2, 3 (then again for 4, 5, 6, ...)
_COLUMNS = ("ABCDEFGH", "JKLMNPQR", "STUVWXYZ")
#: the 100 km row letters; even zones start five letters on
_ROWS = "ABCDEFGHJKLMNPQRSTUV"


@dataclass(frozen=True)
class UtmRef:
    """A UTM position: zone (1..60), latitude band letter, hemisphere ('N' or 'S'), easting and northing (m,
    northing with the 10,000 km false northing in the south)."""

    zone: int
    band: str
    hemisphere: str
    easting_m: float
    northing_m: float

    @property
    def epsg(self) -> int:
        return (32600 if self.hemisphere == "N" else 32700) + self.zone

    def text(self) -> str:
        """E.g. ``18S 323394 E 4307395 N`` (zone and band, metres)."""
        return f"{self.zone}{self.band} {_metres(self.easting_m)} E {_metres(self.northing_m)} N"


def _metres(v: float) -> int:
    """Whole metres, truncated as grid references are, after rounding to the millimetre (a projection's
    499999.9999999 m is 500000 m)."""
    return math.floor(round(v, 3))


def utm_zone(lat_deg: float, lon_deg: float) -> int:
    """The UTM zone of a place, with the exceptions of south-west Norway (32V) and Svalbard (31X-37X)."""
    lon = (lon_deg + 180.0) % 360.0 - 180.0
    zone = int((lon + 180.0) // 6.0) % 60 + 1
    if 56.0 <= lat_deg < 64.0 and 3.0 <= lon < 12.0:
        return 32
    if 72.0 <= lat_deg < 84.0 and 0.0 <= lon < 42.0:
        return 31 if lon < 9.0 else 33 if lon < 21.0 else 35 if lon < 33.0 else 37
    return zone


@lru_cache(maxsize=16)
def _to_utm(epsg: int) -> Transformer:
    return Transformer.from_crs("EPSG:4326", f"EPSG:{epsg}", always_xy=True)


def utm_ref(lat_deg: float, lon_deg: float) -> UtmRef | None:
    """The UTM position of a place on WGS84; None outside 80 S .. 84 N (or for a non-finite input)."""
    if not (math.isfinite(lat_deg) and math.isfinite(lon_deg) and -80.0 <= lat_deg < 84.0):
        return None
    zone = utm_zone(lat_deg, lon_deg)
    hemisphere = "N" if lat_deg >= 0.0 else "S"
    band = _BANDS[min(int((lat_deg + 80.0) // 8.0), len(_BANDS) - 1)]
    ref = UtmRef(zone, band, hemisphere, 0.0, 0.0)
    e, n = _to_utm(ref.epsg).transform(lon_deg, lat_deg)
    return UtmRef(zone, band, hemisphere, float(e), float(n))


def mgrs_ref(lat_deg: float, lon_deg: float) -> str | None:
    """The MGRS grid reference at 1 m, e.g. ``18S UJ 23394 07395``; None where :func:`utm_ref` is."""
    u = utm_ref(lat_deg, lon_deg)
    if u is None:
        return None
    east, north = _metres(u.easting_m), _metres(u.northing_m)
    column = _COLUMNS[(u.zone - 1) % 3][east // 100_000 - 1]
    row = _ROWS[(north // 100_000 + (5 if u.zone % 2 == 0 else 0)) % len(_ROWS)]
    e, n = east % 100_000, north % 100_000
    return f"{u.zone}{u.band} {column}{row} {e:05d} {n:05d}"
