"""Building footprints as users have them, validated on load and brought into the scene's CRS.

GeoJSON is read here, field by field, so that a broken file gets an error naming the
feature; GeoPackage, Shapefile, SpatiaLite and every other vector format GDAL reads go
through pyogrio. Their CRS is the file's (a GeoJSON's legacy ``crs`` member; RFC 7946's
WGS84 longitude/latitude when it has none), and pyproj reprojects them into the scene's.
Each feature may carry ``id`` and a ``height`` property (metres above ground).
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely
from rasterio.crs import CRS
from shapely.geometry import MultiPolygon, Polygon, mapping, shape

from .errors import InputError
from .raster import crs_name, parse_crs

log = logging.getLogger(__name__)
WGS84 = CRS.from_epsg(4326)
GEOJSON_SUFFIXES = (".geojson", ".json")


@dataclass
class Footprint:
    """One building footprint.

    Attributes
    ----------
    id : str
        Feature id (or its index when the feature has none).
    polygon : shapely Polygon or MultiPolygon
        Outline in world coordinates, metres.
    height : float or None
        Height above ground from the ``height`` property, metres.
    properties : dict
        All properties of the feature.
    """

    id: str
    polygon: Polygon | MultiPolygon
    height: float | None
    properties: dict


def read_footprints(
    path: str | os.PathLike,
    *,
    crs: CRS | None = None,
    extent: tuple[float, float, float, float] | None = None,
) -> list[Footprint]:
    """Read and validate footprints, in the scene's CRS.

    Self-intersecting polygons are kept (``polygon.is_valid`` is False): the modeling
    steps decide whether to repair or skip them, and say so.

    Parameters
    ----------
    path : path
        GeoJSON, GeoPackage, Shapefile, SpatiaLite, or any polygon layer GDAL reads.
    crs : CRS, optional
        The scene's CRS: footprints in another are reprojected into it.
    extent : (xmin, ymin, xmax, ymax), optional
        The scene's extent in ``crs``: a file none of whose footprints overlap it is
        refused; it also tells a GeoJSON without CRS in the scene's coordinates from one
        in RFC 7946's longitude/latitude.

    Raises
    ------
    InputError
        Naming the file and the feature for any structural problem; naming both extents
        when the footprints miss the scene.
    """
    if not os.path.exists(path):
        raise InputError(path, None, "file not found")
    if Path(path).suffix.lower() in GEOJSON_SUFFIXES:
        items, declared = _read_geojson(path)
    else:
        items, declared = _read_ogr(path)
    if not items:
        return items
    source = _source_crs(path, items, declared, crs, extent)
    if crs is not None and source is not None and source != crs:
        items = _reprojected(items, source, crs)
    if extent is not None:
        _check_overlap(path, items, extent, crs)
    return items


def _read_geojson(path) -> tuple[list[Footprint], CRS | None]:
    """The features of a GeoJSON FeatureCollection and the CRS its ``crs`` member names."""
    try:
        with open(path) as f:
            doc = json.load(f)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(path, None, f"not valid JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("type") != "FeatureCollection":
        raise InputError(path, "type", "expected a GeoJSON FeatureCollection")
    features = doc.get("features")
    if not isinstance(features, list):
        raise InputError(path, "features", "expected a list of features")
    out = []
    for i, feat in enumerate(features):
        where = f"features[{i}]"
        if not isinstance(feat, dict) or feat.get("type") != "Feature":
            raise InputError(path, where, "not a GeoJSON Feature")
        geom = feat.get("geometry")
        if not isinstance(geom, dict) or geom.get("type") not in ("Polygon", "MultiPolygon"):
            raise InputError(path, f"{where}.geometry", "expected a Polygon or MultiPolygon")
        _check_rings(path, f"{where}.geometry.coordinates", geom)
        try:
            poly = shape(geom)
        except (ValueError, TypeError, AttributeError, shapely.errors.GEOSException) as exc:
            raise InputError(path, f"{where}.geometry", f"invalid geometry ({exc})") from None
        if poly.is_empty or poly.area <= 0:
            raise InputError(path, f"{where}.geometry", "polygon has no area")
        props = feat.get("properties") or {}
        if not isinstance(props, dict):
            raise InputError(path, f"{where}.properties", "expected an object")
        height = props.get("height")
        if height is not None:
            if not isinstance(height, int | float) or not height > 0:
                raise InputError(path, f"{where}.properties.height", "expected a positive number")
            height = float(height)
        fid = feat.get("id", props.get("id", i))
        out.append(Footprint(str(fid), poly, height, props))
    declared = None
    member = doc.get("crs")
    if member is not None:
        name = member.get("properties", {}).get("name") if isinstance(member, dict) else None
        if not isinstance(name, str):
            raise InputError(path, "crs.properties.name", "expected the name of a CRS")
        declared = parse_crs(name, path=path, field="crs")  # an OGC URN, EPSG code or WKT
    return out, declared


def _read_ogr(path) -> tuple[list[Footprint], CRS | None]:
    """The polygons of a vector file GDAL reads (pyogrio) and its layer's CRS."""
    import pyogrio

    try:
        meta, fids, geometry, fields = pyogrio.raw.read(path, return_fids=True)
    except Exception as exc:  # noqa: BLE001 - GDAL raises many types for bad files
        raise InputError(path, None, f"not a readable vector file ({exc})") from None
    if geometry is None:
        raise InputError(path, "geometry", "the layer has no geometry")
    names = [str(n) for n in meta["fields"]]
    columns = dict(zip(names, fields, strict=True))
    out = []
    for i, wkb in enumerate(geometry):
        where = f"feature {fids[i] if fids is not None else i}"
        poly = shapely.from_wkb(wkb) if wkb is not None else None
        if poly is None or poly.geom_type not in ("Polygon", "MultiPolygon"):
            kind = "none" if poly is None else poly.geom_type
            raise InputError(path, f"{where}.geometry", f"expected a Polygon, got {kind}")
        if poly.is_empty or poly.area <= 0:
            raise InputError(path, f"{where}.geometry", "polygon has no area")
        props = {k: _plain(v[i]) for k, v in columns.items()}
        height = props.get("height")
        if height is not None and not (isinstance(height, int | float) and height > 0):
            raise InputError(path, f"{where}.height", "expected a positive number")
        fid = props.get("id", fids[i] if fids is not None else i)
        out.append(Footprint(str(fid), shapely.force_2d(poly), height, props))
    crs = parse_crs(meta["crs"], path=path, field="crs") if meta.get("crs") else None
    return out, crs


def _plain(value):
    """A NumPy scalar as the Python value JSON writes."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def _bounds(items: list[Footprint]) -> np.ndarray:
    return np.asarray(shapely.total_bounds([f.polygon for f in items]))


def _overlaps(bounds, extent) -> bool:
    x0, y0, x1, y1 = bounds
    return x0 < extent[2] and x1 > extent[0] and y0 < extent[3] and y1 > extent[1]


def _source_crs(path, items, declared, crs, extent) -> CRS | None:
    """The CRS the file's coordinates are in: the one it names; else WGS84 (RFC 7946)
    when they can be longitudes and latitudes and land in the scene; else the scene's
    own when they lie in its extent; else a one-line error."""
    if declared is not None:
        return declared
    b = _bounds(items)
    lonlat = b[0] >= -180 and b[2] <= 180 and b[1] >= -90 and b[3] <= 90
    if crs is None:
        return None
    if lonlat and Path(path).suffix.lower() in GEOJSON_SUFFIXES:
        in_scene = _bounds(_reprojected(items, WGS84, crs))
        if extent is None or _overlaps(in_scene, extent):
            log.info("%s: no CRS named; read as RFC 7946 WGS84 longitude/latitude", path)
            return WGS84
    if extent is None or _overlaps(b, extent):
        log.info("%s: no CRS named; its coordinates lie in the scene's, taken as its CRS", path)
        return crs
    raise InputError(
        path, "crs", f"names no CRS, and its coordinates {_fmt(b)} are neither WGS84 "
        f"longitude/latitude nor in the scene's extent {_fmt(extent)}; give the file a CRS",
    )  # fmt: skip


def _reprojected(items: list[Footprint], source: CRS, target: CRS) -> list[Footprint]:
    """The footprints moved from ``source`` to ``target`` (pyproj, x = easting/longitude)."""
    from pyproj import Transformer

    move = Transformer.from_crs(source.to_wkt(), target.to_wkt(), always_xy=True)
    polys = shapely.transform(
        np.array([f.polygon for f in items], dtype=object),
        lambda xy: np.column_stack(move.transform(xy[:, 0], xy[:, 1])),
    )
    return [Footprint(f.id, p, f.height, f.properties) for f, p in zip(items, polys, strict=True)]


def _check_overlap(path, items, extent, crs) -> None:
    b = _bounds(items)
    if not _overlaps(b, extent):
        where = f" (in {crs_name(crs)})" if crs is not None else ""
        raise InputError(
            path, None, f"the footprints' extent {_fmt(b)}{where} misses the scene's extent "
            f"{_fmt(extent)}",
        )  # fmt: skip


def _fmt(b) -> str:
    return "(" + ", ".join(f"{v:.6g}" for v in b) + ")"


def _check_rings(path, where: str, geom: dict) -> None:
    coords = geom.get("coordinates")
    polys = [coords] if geom["type"] == "Polygon" else coords
    if not isinstance(polys, list) or not polys:
        raise InputError(path, where, "expected a list of rings")
    for p, rings in enumerate(polys):
        if not isinstance(rings, list) or not rings:
            raise InputError(path, where, f"polygon {p} has no rings")
        for r, ring in enumerate(rings):
            ok = isinstance(ring, list) and all(
                isinstance(pt, list)
                and len(pt) in (2, 3)
                and all(isinstance(c, int | float) for c in pt)
                for pt in ring
            )
            if not ok:
                raise InputError(path, f"{where} ring {r}", "expected [x, y] number pairs")
            if len(ring) < 4 or ring[0][:2] != ring[-1][:2]:
                raise InputError(path, f"{where} ring {r}", "ring must be closed, >= 4 positions")


def footprints_geojson(items: list[dict], crs: CRS | None = None) -> dict:
    """A FeatureCollection from dicts with ``id``, ``polygon`` and ``properties``, its CRS
    named in a (2008 GeoJSON) ``crs`` member: an OGC URN for an EPSG code, else WKT."""
    doc = {"type": "FeatureCollection", "features": []}
    if crs is not None:
        epsg = crs.to_epsg()
        name = f"urn:ogc:def:crs:EPSG::{epsg}" if epsg else crs.to_wkt()
        doc["crs"] = {"type": "name", "properties": {"name": name}}
    # 0.1 mm: in metres for a projected CRS, in degrees (1e-9) for longitudes and latitudes
    grid = 1e-4 if crs is not None and crs.is_projected else 1e-9
    for it in items:
        geom = mapping(shapely.set_precision(it["polygon"], grid))
        doc["features"].append(
            {
                "type": "Feature",
                "id": it["id"],
                "geometry": _to_lists(geom),
                "properties": it.get("properties", {}),
            }
        )
    return doc


def _to_lists(obj):
    if isinstance(obj, dict):
        return {k: _to_lists(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_to_lists(v) for v in obj]
    return obj
