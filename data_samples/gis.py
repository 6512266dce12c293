"""GIS-style footprints: what an OpenStreetMap outline with zonal heights looks like.

Each true footprint is displaced by 1 to 2 m, slightly rotated, scaled and
jittered, simplified, and given a height over-estimated by 30 to 70 %.
"""

from __future__ import annotations

import numpy as np
import shapely
from shapely import affinity
from shapely.geometry import Polygon


def _jitter(poly: Polygon, amount: float, rng) -> Polygon:
    def ring(coords):
        c = np.asarray(coords)[:-1]
        c = c + rng.uniform(-amount, amount, c.shape)
        return np.vstack([c, c[:1]])

    return Polygon(ring(poly.exterior.coords), [ring(r.coords) for r in poly.interiors])


def gis_footprint(true_poly: Polygon, true_height: float, rng) -> tuple[Polygon, float, dict]:
    """One distorted footprint, its over-estimated height and what was done to it."""
    shift = rng.uniform(1.0, 2.0)
    direction = rng.uniform(0, 2 * np.pi)
    rot = rng.uniform(-2.0, 2.0)
    scale = rng.uniform(0.97, 1.03)
    p = affinity.rotate(true_poly, rot, origin="centroid")
    p = affinity.scale(p, scale, scale, origin="centroid")
    p = affinity.translate(p, shift * np.cos(direction), shift * np.sin(direction))
    p = _jitter(p, 0.25, rng)
    tol = rng.uniform(0.3, 0.8)
    p = p.simplify(tol, preserve_topology=True)
    if not p.is_valid:
        p = shapely.make_valid(p)
        p = max(shapely.get_parts(p), key=lambda g: g.area if isinstance(g, Polygon) else 0)
    over = rng.uniform(1.3, 1.7)
    height = float(np.round(true_height * over * 2) / 2)
    info = {
        "shift_m": round(float(shift), 3),
        "rotation_deg": round(float(rot), 3),
        "scale": round(float(scale), 4),
        "simplify_m": round(float(tol), 3),
        "height_factor": round(float(over), 3),
    }
    return p, height, info
