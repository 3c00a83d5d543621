"""The classes of the multi-class OSM raster, SegLocNet-NM's map input (the paper's rasterized
SD map, like OrienterNet's): one constant, :data:`OSM_CLASSES`, says which OSM features each
channel draws and how. Pure tag logic; the reader (:mod:`.osm`) keeps the features these tags
select, the rasterizer (:func:`.raster.rasterize_osm_classes`) draws them.

Channels are independent {0, 1} masks (a pixel may be in several: a footway crossing a street
is in ``path`` and in that street's road class). Lines (the ``highway`` ways) are drawn from
their OSM centrelines buffered to the class's fixed width, never from the simulator's world or
a dataset's HD map; areas are filled polygons (holes kept).
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class OsmClass:
    """One channel of the OSM class raster.

    Attributes:
      name: channel name.
      width: line width in metres (a way's centreline buffered by ``width / 2``, round caps);
        None: an area class (filled polygons).
      tags: ``(key, values)`` pairs: an OSM feature belongs to the class when its tag ``key``
        has one of ``values`` (``("*",)``: any value but ``no``).
    """

    name: str
    width: float | None
    tags: tuple[tuple[str, tuple[str, ...]], ...]

    def matches(self, key: str, value: str | None) -> bool:
        for k, values in self.tags:
            if k == key and value is not None:
                if values == ("*",):
                    return value != "no"
                return value in values
        return False


ROAD_WIDTH_M = 2.0  # every road class: a thin line, so that classes and junctions stay apart
PATH_WIDTH_M = 1.0

# The channels, in raster order (9). Roads are the drivable highway classes of
# ``osm.HIGHWAY_LANES`` (every one in exactly one road channel, pinned by a test); ``path`` the
# ways a car does not drive on; ``building`` the footprints of the HD / SD maps.
OSM_CLASSES: tuple[OsmClass, ...] = (
    OsmClass(
        "road_major",
        ROAD_WIDTH_M,
        (
            (
                "highway",
                (
                    "motorway",
                    "trunk",
                    "primary",
                    "motorway_link",
                    "trunk_link",
                    "primary_link",
                ),
            ),
        ),
    ),
    OsmClass(
        "road_secondary",
        ROAD_WIDTH_M,
        (("highway", ("secondary", "tertiary", "secondary_link", "tertiary_link")),),
    ),
    OsmClass(
        "road_minor",
        ROAD_WIDTH_M,
        (("highway", ("residential", "unclassified", "living_street", "road")),),
    ),
    OsmClass("road_service", ROAD_WIDTH_M, (("highway", ("service",)),)),
    OsmClass(
        "path",
        PATH_WIDTH_M,
        (
            (
                "highway",
                (
                    "footway",
                    "cycleway",
                    "path",
                    "pedestrian",
                    "steps",
                    "track",
                    "bridleway",
                ),
            ),
        ),
    ),
    OsmClass("building", None, (("building", ("*",)),)),
    OsmClass("parking", None, (("amenity", ("parking",)),)),
    OsmClass(
        "green",
        None,
        (
            ("leisure", ("park", "garden")),
            ("landuse", ("grass", "forest", "meadow", "village_green", "recreation_ground")),
            ("natural", ("wood", "scrub", "grassland", "heath")),
        ),
    ),
    OsmClass(
        "water",
        None,
        (
            ("natural", ("water",)),
            ("waterway", ("riverbank",)),
            ("landuse", ("reservoir", "basin")),
        ),
    ),
)
OSM_CLASS_NAMES: tuple[str, ...] = tuple(c.name for c in OSM_CLASSES)
LINE_CLASSES = tuple(c for c in OSM_CLASSES if c.width is not None)
AREA_CLASSES = tuple(c for c in OSM_CLASSES if c.width is None and c.name != "building")
# Tag keys of the area classes other than buildings (the reader keeps areas with these).
AREA_KEYS = tuple(dict.fromkeys(k for c in AREA_CLASSES for k, _ in c.tags))


def line_class(highway: str | None) -> OsmClass | None:
    """The line class of a ``highway`` way (None: drawn in no channel)."""
    return next((c for c in LINE_CLASSES if c.matches("highway", highway)), None)


def area_class(tags) -> OsmClass | None:
    """The area class (not ``building``: the reader keeps buildings apart) of an OSM area's
    ``tags`` (a mapping; the first class in channel order wins), None: drawn in no channel."""
    for c in AREA_CLASSES:
        if any(c.matches(k, tags.get(k)) for k, _ in c.tags):
            return c
    return None


def spec() -> dict:
    """The class table as plain JSON (the manifest records it with the stored rasters; a raster
    drawn with another table is drawn again)."""
    return {
        "channels": list(OSM_CLASS_NAMES),
        "widths": {c.name: c.width for c in LINE_CLASSES},
        "tags": {c.name: {k: list(v) for k, v in c.tags} for c in OSM_CLASSES},
    }
