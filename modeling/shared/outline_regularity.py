"""Regular building outlines (the LOD paper, section 5.2): the sides of an outline that
run near the building's dominant direction, or square to it, are turned onto it exactly,
and the corners moved to where the straightened sides meet.

Polygonised cells leave outlines that are straight only up to the simplification's
tolerance: a rectangle comes out with sides a few degrees off and corners cut. Buildings
are mostly rectilinear, so the LOD paper reorients segments near the facade directions to
them and merges collinear ones; here the same is done on the outline of a roof-face
coverage, moving each outline vertex (and so every face that shares it) and dropping the
outline vertices left in the middle of a straight side.
"""

from __future__ import annotations

import numpy as np
import shapely
from shapely.geometry import Polygon

_KEY = 1e-6  # metres: coordinates closer than this are one vertex


def dominant_direction(
    rings: list[np.ndarray], tolerance_deg: float = 10.0, max_jog: float = 0.0
) -> float:
    """The building's main direction, radians in [-pi/4, pi/4).

    First the length-weighted mean of the edges' directions modulo 90 degrees, refined
    over the edges within ``tolerance_deg`` of it; then the same mean over the chords of
    the sides (:func:`ring_sides`): a side polygonised from cells at a slant is a
    staircase of long edges and short jogs, and only its chord has its direction.

    Parameters
    ----------
    rings : list of (K, 2) arrays
        Closed rings (first vertex repeated last), metres.
    tolerance_deg : float
    max_jog : float
        Longest jog within a side, metres.
    """
    d = np.concatenate([np.diff(r, axis=0) for r in rings])
    length = np.hypot(d[:, 0], d[:, 1])
    angle = np.arctan2(d[:, 1], d[:, 0])
    theta = np.angle(np.sum(length * np.exp(4j * angle))) / 4
    near = np.abs(_off_axis(angle, theta)) < np.radians(tolerance_deg)
    if near.any():
        theta = np.angle(np.sum(length[near] * np.exp(4j * angle[near]))) / 4
    chords = []
    for r in rings:
        side, _ = ring_sides(r[:-1], theta, tolerance_deg, max_jog)
        e = np.diff(r, axis=0)
        chords += [e[side == s].sum(axis=0) for s in range(side.max() + 1)]
    if chords:
        c = np.asarray(chords)
        theta = (
            np.angle(np.sum(np.hypot(c[:, 0], c[:, 1]) * np.exp(4j * np.arctan2(c[:, 1], c[:, 0]))))
            / 4
        )
    return float(theta)


def _off_axis(angle: np.ndarray, theta: float) -> np.ndarray:
    """Signed angle from each direction to the nearest of theta + k * 90 degrees."""
    return (angle - theta + np.pi / 4) % (np.pi / 2) - np.pi / 4


def ring_sides(
    ring: np.ndarray, theta: float, tolerance_deg: float, max_jog: float
) -> tuple[np.ndarray, np.ndarray]:
    """The side of each edge of a ring (-1: none) and its axis (0: theta, 1: square).

    A side is a run of consecutive edges within ``tolerance_deg`` of one axis, with the
    jogs between them: edges off the axes shorter than ``max_jog`` between two edges of
    the same axis.

    Parameters
    ----------
    ring : (K, 2)
        Open ring (first vertex not repeated), metres.
    """
    d = np.roll(ring, -1, axis=0) - ring
    length = np.hypot(d[:, 0], d[:, 1])
    angle = np.arctan2(d[:, 1], d[:, 0])
    aligned = (np.abs(_off_axis(angle, theta)) < np.radians(tolerance_deg)) & (length > 0)
    axis = np.round((angle - theta) / (np.pi / 2)).astype(int) % 2
    prev, nxt = np.roll(np.arange(len(ring)), 1), np.roll(np.arange(len(ring)), -1)
    jog = ~aligned & (length < max_jog) & aligned[prev] & aligned[nxt] & (axis[prev] == axis[nxt])
    aligned, axis = aligned | jog, np.where(jog, axis[prev], axis)
    same = aligned & aligned[prev] & (axis == axis[prev])
    run = np.cumsum(~same) - 1
    run[run < 0] = run.max() if (~same).any() else 0  # the run through the ring's start
    side = np.full(len(ring), -1)
    side[aligned] = np.unique(run[aligned], return_inverse=True)[1]
    return side, axis


def regular_ring(
    ring: np.ndarray, theta: float, tolerance_deg: float, max_shift: float
) -> tuple[np.ndarray, np.ndarray]:
    """New positions of a ring's vertices with its sides (:func:`ring_sides`, jogs up to
    ``max_shift``) on the axes.

    Each side's line keeps the length-weighted mean offset of its edges. A vertex inside
    a side is projected onto it; a vertex between two sides goes to where they meet; a
    vertex between a side and an edge off the axes goes to where that edge's line crosses
    the side, unless that edge is shorter than ``max_shift`` between two square sides (a
    cut corner): both its ends then go to the corner. A vertex that would move more than
    ``max_shift`` stays.

    Parameters
    ----------
    ring : (K, 2)
        Open ring (first vertex not repeated), metres.
    theta : float
        Dominant direction, radians.

    Returns
    -------
    (K, 2) new positions, and (K,) bool: vertices moved onto the middle of a side.
    """
    k = len(ring)
    side, axis = ring_sides(ring, theta, tolerance_deg, max_shift)
    start, end = ring, np.roll(ring, -1, axis=0)
    d = end - start
    length = np.hypot(d[:, 0], d[:, 1])
    n_sides = side.max() + 1
    direction = np.stack([np.cos(theta + axis * np.pi / 2), np.sin(theta + axis * np.pi / 2)], 1)
    normal = np.stack([-direction[:, 1], direction[:, 0]], axis=1)
    offset = np.einsum("ij,ij->i", normal, (start + end) / 2)
    line_normal = np.zeros((max(n_sides, 1), 2))
    line_offset = np.zeros(max(n_sides, 1))
    for s in range(n_sides):
        mine = side == s
        line_normal[s] = normal[mine][0]
        line_offset[s] = np.average(offset[mine], weights=length[mine])

    out = ring.copy()
    inner = np.zeros(k, bool)
    for i in range(k):
        before, after = side[i - 1], side[i]
        if before < 0 and after < 0:
            continue
        if before == after:
            n, c = line_normal[after], line_offset[after]
            new = ring[i] - (ring[i] @ n - c) * n
        elif before >= 0 and after >= 0:
            new = _meet(line_normal[before], line_offset[before], line_normal[after],
                        line_offset[after])  # fmt: skip
        else:
            s = before if before >= 0 else after
            j = i if before >= 0 else i - 1  # the edge off the axes
            n_edge = np.array([-d[j, 1], d[j, 0]]) / max(length[j], 1e-12)
            new = _meet(line_normal[s], line_offset[s], n_edge, n_edge @ ring[i])
        if new is not None and np.hypot(*(new - ring[i])) <= max_shift:
            out[i] = new
            inner[i] = before == after
    # a short edge off the axes between two square sides is a corner the simplification
    # cut: both its ends go to the corner
    for j in np.flatnonzero((side < 0) & (length < max_shift)):
        before, after = side[j - 1], side[(j + 1) % k]
        if before < 0 or after < 0 or axis[j - 1] == axis[(j + 1) % k]:
            continue
        corner = _meet(line_normal[before], line_offset[before], line_normal[after],
                       line_offset[after])  # fmt: skip
        ends = [j, (j + 1) % k]
        if corner is not None and np.hypot(*(ring[ends] - corner).T).max() <= max_shift:
            out[ends] = corner
    return out, inner


def _meet(n1: np.ndarray, c1: float, n2: np.ndarray, c2: float) -> np.ndarray | None:
    """The point on the lines n1 . p = c1 and n2 . p = c2; None when near parallel."""
    a = np.array([n1, n2])
    if abs(np.linalg.det(a)) < 0.2:  # under about 12 degrees apart
        return None
    return np.linalg.solve(a, [c1, c2])


def regularise_outline(
    polygons: list[Polygon], tolerance_deg: float = 10.0, max_shift: float = 1.0
) -> list[Polygon]:
    """A roof-face coverage with its outline's near-axis sides put on the building's
    dominant directions (:func:`dominant_direction`, :func:`regular_ring`).

    Every face that shares an outline vertex follows it, so the coverage stays a
    coverage; outline vertices in the middle of a side that no other face shares are
    dropped. If the result is not a valid coverage (a face folded by a move), the
    polygons are returned unchanged.

    Parameters
    ----------
    polygons : list of Polygon
        A coverage (shared boundaries, vertex for vertex), metres.
    tolerance_deg : float
        Edges this close to an axis are put on it.
    max_shift : float
        No vertex moves farther than this, metres.
    """
    if not polygons or tolerance_deg <= 0:
        return polygons
    outline = shapely.coverage_union_all(polygons)
    rings = [np.asarray(r.coords) for p in getattr(outline, "geoms", [outline])
             for r in (p.exterior, *p.interiors)]  # fmt: skip
    theta = dominant_direction(rings, tolerance_deg, max_shift)
    moved: dict[tuple, np.ndarray] = {}
    drop: set[tuple] = set()
    for ring in rings:
        new, inner = regular_ring(ring[:-1], theta, tolerance_deg, max_shift)
        for p, q, mid in zip(ring[:-1], new, inner, strict=True):
            moved[_key(p)] = q
            if mid:
                drop.add(_key(p))
    uses: dict[tuple, int] = {}
    for poly in polygons:
        for r in (poly.exterior, *poly.interiors):
            for p in np.asarray(r.coords)[:-1]:
                uses[_key(p)] = uses.get(_key(p), 0) + 1
    drop = {v for v in drop if uses.get(v) == 1}

    def rebuilt(coords: np.ndarray) -> np.ndarray | None:
        keys = [_key(p) for p in coords[:-1]]
        kept = [moved.get(v, p) for v, p in zip(keys, coords[:-1], strict=True) if v not in drop]
        kept = [p for p, q in zip(kept, kept[1:] + kept[:1], strict=True) if _key(p) != _key(q)]
        return np.asarray(kept) if len(kept) >= 3 else None

    out = []
    for poly in polygons:
        shell = rebuilt(np.asarray(poly.exterior.coords))
        holes = [rebuilt(np.asarray(r.coords)) for r in poly.interiors]
        if shell is None or any(h is None for h in holes):
            return polygons
        out.append(Polygon(shell, holes))
    if not all(p.is_valid and p.area > 0 for p in out):
        return polygons
    if not shapely.coverage_is_valid(np.array(out, dtype=object)):
        return polygons
    return out


def _key(p: np.ndarray) -> tuple[int, int]:
    return (int(round(p[0] / _KEY)), int(round(p[1] / _KEY)))
