"""The ``map`` config section (``conf/map/*.yaml``) as typed configs: where the city comes from
(:class:`CitySource`) and how it is rasterized (:class:`~seglocnet_jax.maps.raster.MapConfig`)."""

from __future__ import annotations

import dataclasses

from seglocnet_jax.config_util import ConfigError, from_dict
from seglocnet_jax.maps.osm import CityGeometry, load_city
from seglocnet_jax.maps.projection import ProjectionError, make_projection
from seglocnet_jax.maps.raster import MapConfig


@dataclasses.dataclass(frozen=True)
class CitySource:
    """Which OSM data, in which world frame.

    Attributes:
      city: embedded city (``helsinki``, ``kouvola``) or a ``.osm.pbf`` / ``.osm`` path.
      projection: ``tmerc`` (centred on the data or on ``origin_latlon``), ``utm`` or
        ``topocentric`` (see :mod:`seglocnet_jax.maps.projection`).
      utm_zone: UTM zone number (utm only).
      origin_latlon: ``[lat, lon]`` degrees of the world origin.
      utm_origin_en: ``[easting, northing]`` metres subtracted from UTM (utm, instead of
        ``origin_latlon``; Argoverse 1.1 publishes these).
      bbox: optional requested area ``[west, south, east, north]`` degrees.
    """

    city: str = "helsinki"
    projection: str = "tmerc"
    utm_zone: int | None = None
    origin_latlon: tuple[float, float] | None = None
    utm_origin_en: tuple[float, float] | None = None
    bbox: tuple[float, float, float, float] | None = None

    def __post_init__(self):
        try:
            self.make_projection()
        except ProjectionError as err:
            raise ConfigError(str(err)) from err
        if self.bbox is not None and len(self.bbox) != 4:
            raise ConfigError(f"map.bbox must be [west, south, east, north], got {self.bbox!r}")

    def make_projection(self):
        return make_projection(
            self.projection, self.origin_latlon, self.utm_zone, self.utm_origin_en
        )

    def load(self) -> CityGeometry:
        """Reads and projects the city (:func:`seglocnet_jax.maps.load_city`)."""
        return load_city(self.city, self.make_projection(), self.bbox)


SOURCE_KEYS = tuple(f.name for f in dataclasses.fields(CitySource))
RASTER_KEYS = tuple(f.name for f in dataclasses.fields(MapConfig))


def configs_from_section(section: dict | None, prefix: str = "map"):
    """``(CitySource, MapConfig)`` of a plain-dict ``map`` section; unknown keys and bad values
    raise :class:`ConfigError` naming ``map.<key>``."""
    section = dict(section or {})
    unknown = sorted(set(section) - set(SOURCE_KEYS) - set(RASTER_KEYS))
    if unknown:
        raise ConfigError(
            f"unknown config key(s) {', '.join(f'{prefix}.{k}' for k in unknown)}; "
            f"{prefix} accepts: {', '.join(sorted(SOURCE_KEYS + RASTER_KEYS))}"
        )
    source = from_dict(CitySource, {k: v for k, v in section.items() if k in SOURCE_KEYS}, prefix)
    raster = from_dict(MapConfig, {k: v for k, v in section.items() if k in RASTER_KEYS}, prefix)
    return source, raster
