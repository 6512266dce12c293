"""Building footprints as GeoJSON polygons, validated on load.

Coordinates are in the scene's CRS (projected metres), not WGS84: a legacy
``crs`` member may name it. Each feature may carry ``id`` and a ``height``
property (metres above ground).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass

import shapely
from shapely.geometry import MultiPolygon, Polygon, mapping, shape

from .errors import InputError


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


def read_footprints(path: str | os.PathLike) -> list[Footprint]:
    """Read and validate a GeoJSON FeatureCollection of Polygon/MultiPolygon features.

    Self-intersecting polygons are kept (``polygon.is_valid`` is False): the modeling
    steps decide whether to repair or skip them, and say so.

    Raises
    ------
    InputError
        Naming the file and the feature for any structural problem.
    """
    if not os.path.exists(path):
        raise InputError(path, None, "file not found")
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
    return out


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


def footprints_geojson(items: list[dict], crs_name: str | None = None) -> dict:
    """A FeatureCollection from dicts with ``id``, ``polygon`` and ``properties``."""
    doc = {"type": "FeatureCollection", "features": []}
    if crs_name:
        doc["crs"] = {"type": "name", "properties": {"name": crs_name}}
    for it in items:
        geom = mapping(shapely.set_precision(it["polygon"], 1e-4))
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
