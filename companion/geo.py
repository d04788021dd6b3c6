"""Local NED <-> WGS-84 around a home position (flat-earth approximation).

PX4 projects global positions to its local frame with an azimuthal equidistant projection
around the EKF origin. Indoors and over a few hundred metres an equirectangular (flat-earth)
approximation agrees with it to millimetres, so that is what we use::

    north_m = (lat - lat0) * R
    east_m  = (lon - lon0) * R * cos(lat0)
    down_m  = alt0 - alt_amsl

with ``R`` the WGS-84 equatorial radius and angles in radians. Errors grow with the square
of the distance from home (about 1 cm at 1 km); do not use it for long-range navigation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

EARTH_RADIUS_M = 6_378_137.0


@dataclass(frozen=True)
class GeoOrigin:
    """The home position: WGS-84 latitude/longitude in degrees, altitude AMSL in metres.

    The default is PX4 SITL's default home (Zurich, Irchel park).
    """

    lat_deg: float = 47.397742
    lon_deg: float = 8.545594
    alt_m: float = 488.0

    def __post_init__(self) -> None:
        if not -90.0 <= self.lat_deg <= 90.0:
            raise ValueError(f"latitude must be in [-90, 90] degrees (got {self.lat_deg})")
        if not -180.0 <= self.lon_deg <= 180.0:
            raise ValueError(f"longitude must be in [-180, 180] degrees (got {self.lon_deg})")

    def to_ned(self, lat_deg: float, lon_deg: float, alt_m: float) -> tuple[float, float, float]:
        """Local NED (north, east, down) in metres of a global position (alt AMSL)."""
        north = math.radians(lat_deg - self.lat_deg) * EARTH_RADIUS_M
        east = (math.radians(lon_deg - self.lon_deg) * EARTH_RADIUS_M
                * math.cos(math.radians(self.lat_deg)))
        return north, east, self.alt_m - alt_m

    def to_global(self, north_m: float, east_m: float, down_m: float) -> tuple[float, float, float]:
        """(lat_deg, lon_deg, alt_m AMSL) of a local NED position in metres."""
        lat = self.lat_deg + math.degrees(north_m / EARTH_RADIUS_M)
        lon = self.lon_deg + math.degrees(
            east_m / (EARTH_RADIUS_M * math.cos(math.radians(self.lat_deg)))
        )
        return lat, lon, self.alt_m - down_m
