"""WGS84 longitude/latitude <-> a city's local metric world frame (x east, y north, metres).

The one seam to pyproj. Three kinds, matching the world frames the project meets:

* ``tmerc`` (default): a transverse Mercator centred on the city (scale 1 on the central
  meridian, origin at ``origin_latlon``); grid north equals true north at the centre, and the scale
  error stays below 1e-7 within a few km.
* ``utm``: UTM zone ``utm_zone`` minus a metric origin (Argoverse city frames: the origin is given
  as ``utm_origin_en`` easting/northing, or as ``origin_latlon`` projected through the zone).
  Grid north differs from true north by the meridian convergence (PIT +0.64 deg), which is why
  OSM must go through the same zone as the dataset.
* ``topocentric``: the local tangent plane (east, north) at ``origin_latlon`` on the WGS84
  ellipsoid (nuScenes map frames). Points are taken on the ellipsoid (height 0); the inverse
  solves for the up component by a short fixed-point iteration.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pyproj

KINDS = ("tmerc", "utm", "topocentric")


class ProjectionError(ValueError):
    """A projection is mis-specified; the message names the parameter and the bad value."""


@functools.lru_cache(maxsize=64)
def _transformer(definition: str) -> pyproj.Transformer:
    if definition.startswith("+proj=pipeline"):
        return pyproj.Transformer.from_pipeline(definition)
    return pyproj.Transformer.from_crs("EPSG:4326", definition, always_xy=True)


@dataclasses.dataclass(frozen=True)
class Projection:
    """How OSM longitude/latitude become world metres.

    Attributes:
      kind: ``"tmerc"``, ``"utm"`` or ``"topocentric"``.
      origin_latlon: ``(lat, lon)`` degrees of the world origin (tmerc / topocentric; utm when
        ``utm_origin_en`` is not given).
      utm_zone: UTM zone number 1..60 (utm only).
      utm_origin_en: ``(easting, northing)`` metres subtracted from UTM coordinates (utm only).
      south: southern-hemisphere UTM zone (utm only).
    """

    kind: str = "tmerc"
    origin_latlon: tuple[float, float] | None = None
    utm_zone: int | None = None
    utm_origin_en: tuple[float, float] | None = None
    south: bool = False

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ProjectionError(f"map.projection must be one of {KINDS}, got {self.kind!r}")
        if self.origin_latlon is not None:
            lat, lon = (float(v) for v in self.origin_latlon)
            if not (-90 <= lat <= 90 and -180 <= lon <= 180):
                raise ProjectionError(
                    f"map.origin_latlon must be (lat, lon) degrees, got {self.origin_latlon!r}"
                )
            object.__setattr__(self, "origin_latlon", (lat, lon))
        if self.kind == "utm":
            if self.utm_zone is None or not 1 <= int(self.utm_zone) <= 60:
                raise ProjectionError(f"map.utm_zone must be 1..60 for utm, got {self.utm_zone!r}")
            if self.origin_latlon is None and self.utm_origin_en is None:
                raise ProjectionError("utm projection needs map.origin_latlon or utm_origin_en")
        elif self.origin_latlon is None:
            raise ProjectionError(f"{self.kind} projection needs map.origin_latlon (lat, lon)")

    # ----------------------------------------------------------------------- constructors

    @classmethod
    def tmerc(cls, lat: float, lon: float) -> Projection:
        """Transverse Mercator centred on ``(lat, lon)`` degrees."""
        return cls("tmerc", (lat, lon))

    @classmethod
    def utm(cls, zone: int, origin_latlon=None, origin_en=None, south: bool = False) -> Projection:
        """UTM ``zone`` minus ``origin_en`` (metres) or the projected ``origin_latlon``."""
        en = None if origin_en is None else (float(origin_en[0]), float(origin_en[1]))
        return cls("utm", origin_latlon, int(zone), en, south)

    @classmethod
    def topocentric(cls, lat: float, lon: float) -> Projection:
        """Local east/north tangent plane at ``(lat, lon)`` degrees."""
        return cls("topocentric", (lat, lon))

    # ----------------------------------------------------------------------- transforms

    def _definition(self) -> str:
        if self.kind == "tmerc":
            lat, lon = self.origin_latlon
            return (
                f"+proj=tmerc +lat_0={lat!r} +lon_0={lon!r} +k=1 +x_0=0 +y_0=0 "
                "+ellps=WGS84 +units=m +no_defs"
            )
        if self.kind == "utm":
            south = " +south" if self.south else ""
            return f"+proj=utm +zone={int(self.utm_zone)}{south} +datum=WGS84 +units=m +no_defs"
        lat, lon = self.origin_latlon
        return (
            "+proj=pipeline +step +proj=cart +ellps=WGS84 "
            f"+step +proj=topocentric +ellps=WGS84 +lat_0={lat!r} +lon_0={lon!r}"
        )

    @functools.cached_property
    def _offset(self) -> tuple[float, float]:
        if self.kind != "utm":
            return (0.0, 0.0)
        if self.utm_origin_en is not None:
            return self.utm_origin_en
        lat, lon = self.origin_latlon
        e, n = _transformer(self._definition()).transform(lon, lat)
        return (float(e), float(n))

    def to_metric(self, lon, lat) -> tuple[np.ndarray, np.ndarray]:
        """Degrees (any matching shapes) to world ``(x east, y north)`` metres, float64."""
        lon = np.asarray(lon, np.float64)
        lat = np.asarray(lat, np.float64)
        t = _transformer(self._definition())
        if self.kind == "topocentric":
            x, y, _ = t.transform(lon, lat, np.zeros_like(lon))
        else:
            x, y = t.transform(lon, lat)
        ox, oy = self._offset
        return np.asarray(x, np.float64) - ox, np.asarray(y, np.float64) - oy

    def to_lonlat(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """World metres (any matching shapes) to ``(lon, lat)`` degrees, float64."""
        ox, oy = self._offset
        x = np.asarray(x, np.float64) + ox
        y = np.asarray(y, np.float64) + oy
        t = _transformer(self._definition())
        if self.kind != "topocentric":
            lon, lat = t.transform(x, y, direction="INVERSE")
            return np.asarray(lon, np.float64), np.asarray(lat, np.float64)
        # The plane point (x, y) is the ellipsoid point whose (east, north) are (x, y): find its
        # up component u (about -(x^2 + y^2) / 2R) by iterating u <- up(inverse(x, y, u), h=0).
        up = np.zeros_like(x)
        for _ in range(4):  # converges by ~1e-4 per step at city scale: 4 steps are < 1 um
            lon, lat, _ = t.transform(x, y, up, direction="INVERSE")
            _, _, up = t.transform(lon, lat, np.zeros_like(x))
        lon, lat, _ = t.transform(x, y, up, direction="INVERSE")
        return np.asarray(lon, np.float64), np.asarray(lat, np.float64)


def make_projection(
    kind: str | None = "tmerc",
    origin_latlon=None,
    utm_zone=None,
    utm_origin_en=None,
    south: bool = False,
) -> Projection | None:
    """A :class:`Projection` from config values; ``None`` when ``kind`` is tmerc (or None) and no
    origin is given, meaning "centre a transverse Mercator on the data" (see ``osm.load_city``)."""
    kind = kind or "tmerc"
    if kind == "tmerc" and origin_latlon is None:
        return None
    origin = None if origin_latlon is None else tuple(origin_latlon)
    en = None if utm_origin_en is None else tuple(utm_origin_en)
    return Projection(kind, origin, None if utm_zone is None else int(utm_zone), en, south)
