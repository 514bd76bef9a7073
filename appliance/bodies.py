"""Planetary bodies: radius for curvature, default atmospheric refraction, and geodesic distance."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from functools import cached_property

from pyproj import Geod

from appliance.errors import ConfigError


class BodyName(str, enum.Enum):
    EARTH = "earth"
    MOON = "moon"
    MARS = "mars"


@dataclass(frozen=True)
class Body:
    """A body on which the appliance may stand.

    ``radius_m`` is the mean radius used for curvature; ``refraction`` the default coefficient of
    atmospheric refraction k (the effective radius is ``radius_m / (1 - k)``).
    """

    name: BodyName
    radius_m: float
    refraction: float
    semi_major_m: float
    inverse_flattening: float

    def effective_radius_m(self, refraction: float | None = None) -> float:
        k = self.refraction if refraction is None else refraction
        return self.radius_m / (1.0 - k)

    @cached_property
    def geod(self) -> Geod:
        """The body's reference ellipsoid (a sphere where ``inverse_flattening`` is 0)."""
        if self.inverse_flattening == 0.0:
            return Geod(a=self.semi_major_m, f=0.0)
        return Geod(a=self.semi_major_m, rf=self.inverse_flattening)


EARTH = Body(BodyName.EARTH, 6_371_008.8, 0.13, 6_378_137.0, 298.257223563)
MOON = Body(BodyName.MOON, 1_737_400.0, 0.0, 1_737_400.0, 0.0)
MARS = Body(BodyName.MARS, 3_389_500.0, 0.0, 3_396_190.0, 169.894447223612)

BODIES = {b.name.value: b for b in (EARTH, MOON, MARS)}


def geodesic_distance_m(lat1_deg: float, lon1_deg: float, lat2_deg: float, lon2_deg: float,
                        body: Body = EARTH) -> float:
    """Length (m) of the geodesic between two points on ``body``'s ellipsoid (WGS84 on Earth)."""
    _, _, d = body.geod.inv(lon1_deg, lat1_deg, lon2_deg, lat2_deg)
    return float(d)


def body_named(name: str) -> Body:
    try:
        return BODIES[name.lower()]
    except KeyError:
        raise ConfigError(f"unknown body {name!r}: expected one of {', '.join(BODIES)}") from None
