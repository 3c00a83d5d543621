"""Maps from real OpenStreetMap: reading (pyosmium), projection (pyproj) and the unified binary
``(C, H, W)`` raster (rasterio) with its tiles and GT BEV labels; the multi-class OSM raster of
the neural map (:mod:`.osm_classes`)."""

from seglocnet_jax.maps.config import CitySource, configs_from_section
from seglocnet_jax.maps.osm import (
    DRIVABLE_HIGHWAYS,
    EMBEDDED_CITIES,
    Area,
    Building,
    CityGeometry,
    MapError,
    Road,
    Way,
    city_key,
    embedded_city_path,
    load_city,
)
from seglocnet_jax.maps.osm_classes import OSM_CLASS_NAMES, OSM_CLASSES, OsmClass
from seglocnet_jax.maps.projection import Projection, ProjectionError, make_projection
from seglocnet_jax.maps.raster import (
    CHANNELS,
    KINDS,
    CityRaster,
    MapConfig,
    MapConfigError,
    buffer_roads,
    rasterize,
    rasterize_geometries,
    rasterize_osm_classes,
)

__all__ = [
    "Area",
    "CHANNELS",
    "DRIVABLE_HIGHWAYS",
    "EMBEDDED_CITIES",
    "KINDS",
    "Building",
    "CityGeometry",
    "CityRaster",
    "CitySource",
    "MapConfig",
    "MapConfigError",
    "MapError",
    "OSM_CLASSES",
    "OSM_CLASS_NAMES",
    "OsmClass",
    "Projection",
    "ProjectionError",
    "Road",
    "Way",
    "buffer_roads",
    "city_key",
    "configs_from_section",
    "embedded_city_path",
    "load_city",
    "make_projection",
    "rasterize",
    "rasterize_geometries",
    "rasterize_osm_classes",
]
