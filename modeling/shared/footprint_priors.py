"""Footprint priors in competition (the variational paper, eq. 2-4).

A prior is a family's outline in its own frame: a box [u0, u1] x [v0, v1] with notches cut
out of it (none for a rectangle; a corner for an L; the two corners of one side for a T;
the middle of one side for a U; a hole for a courtyard). Its transformation T is a
similarity: a rotation theta and a translation to the segment's centroid, the box's
sides standing for the scale along each axis (an affine map without shear, which is
what an orthographic raster leaves of the paper's homography).

Registration (eq. 2) minimises the mismatch between the segment and the prior's smoothed
indicator over the transformation and the notch sizes (Powell's method, from poses read
off the segment: its main direction, its extent, the notches its bounding box leaves).
Competition (eq. 4) compares the priors' mismatches normalised by each template's
variance with the unknown-object label's cost lambda^2; the labelling's boundary term
rho decides, cell by cell with one graph cut, which cells the winner leaves to the data
term: where they form a part of their own, it competes again (a complex outline
decomposes into parts of the families).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import rasterio.features
from scipy import ndimage, optimize
from shapely import affinity
from shapely.geometry import Polygon, box
from shapely.ops import unary_union

from modeling.shared.outline_regularity import dominant_direction
from workbench.graph_cuts import binary_cut
from workbench.raster import Grid

_EPS_CELLS = 0.5  # width of the prior's smoothed edge, cells of the registration grid
_REGISTRATION_GSD = 0.5  # metres: registration runs on cells no finer than this
_MAX_EVALUATIONS = 400  # Powell's function evaluations per prior
_MARGIN = 0.25  # the domain of eq. 4: the segment's box grown by this share of its size
_JOG_CELLS = 2.0  # a digitised side's steps, cells: jogs within a side, its simplification
# the most of a prior the hidden cells may cover (decompose_outline): a crown's edge
# hides up to 0.16 of a roof on dev seeds 1, 7, 13 and 14, while a crescent of a crown
# the classes call building, with the crown beside it hidden, filled 0.31-0.35 of a
# rectangle that then won
MAX_HIDDEN_SHARE = 0.25


@dataclass
class Prior:
    """A registered footprint prior.

    Attributes
    ----------
    family : str
        rect, L, T, U or courtyard.
    theta : float
        Rotation of the prior's u axis from east, radians.
    origin : (2,) float
        World position of the frame's origin (the segment's centroid), metres.
    box : (4,) float
        u0, u1, v0, v1, metres in the frame.
    notches : list of (4,) float
        Rectangles u0, u1, v0, v1 cut out of the box.
    energy : float
        Eq. 4's normalised mismatch at convergence.
    evaluations : int
    """

    family: str
    theta: float
    origin: np.ndarray
    box: np.ndarray
    notches: list = field(default_factory=list)
    energy: float = float("inf")
    evaluations: int = 0

    def polygon(self) -> Polygon:
        """The outline in world metres."""
        shape = box(self.box[0], self.box[2], self.box[1], self.box[3])
        for n in self.notches:
            shape = shape.difference(box(n[0], n[2], n[1], n[3]))
        return _to_world(shape, self.theta, self.origin)

    def frame_polygon(self, rect: np.ndarray) -> Polygon:
        """A rectangle u0, u1, v0, v1 of the prior's frame, in world metres."""
        return _to_world(box(rect[0], rect[2], rect[1], rect[3]), self.theta, self.origin)

    def wings(self) -> list[np.ndarray]:
        """(4,) rectangles u0, u1, v0, v1 whose union is the outline: the family's arms
        at full length, overlapping where they meet (an L's corner), each roofed alone."""
        u0, u1, v0, v1 = self.box
        if self.family == "rect" or not self.notches:
            return [self.box.copy()]
        if self.family == "L":  # notch at the (u0, v0) corner
            n = self.notches[0]
            return [np.array([u0, u1, n[3], v1]), np.array([n[1], u1, v0, v1])]
        if self.family == "T":  # notches at both corners of the v0 side
            a, b, depth = self.notches[0][1], self.notches[1][0], self.notches[0][3]
            return [np.array([u0, u1, depth, v1]), np.array([a, b, v0, v1])]
        if self.family == "U":  # notch in the middle of the v1 side
            a, b, depth = self.notches[0][0], self.notches[0][1], self.notches[0][2]
            return [np.array([u0, u1, v0, depth]), np.array([u0, a, v0, v1]),
                    np.array([b, u1, v0, v1])]  # fmt: skip
        a, b, c, d = self.notches[0]  # courtyard
        return [np.array([u0, u1, v0, c]), np.array([u0, u1, d, v1]),
                np.array([u0, a, v0, v1]), np.array([b, u1, v0, v1])]  # fmt: skip

    def record(self) -> dict:
        return {
            "family": self.family,
            "transformation": {
                "rotation_deg": round(float(np.degrees(self.theta)), 3),
                "translation_m": [round(float(v), 3) for v in self.origin],
                "box_m": [round(float(v), 3) for v in self.box],
            },
            "notches_m": [[round(float(v), 3) for v in n] for n in self.notches],
            "energy_2d": round(float(self.energy), 5),
            "evaluations": int(self.evaluations),
        }


def _to_world(shape, theta: float, origin: np.ndarray):
    rotated = affinity.rotate(shape, theta, origin=(0, 0), use_radians=True)
    return affinity.translate(rotated, float(origin[0]), float(origin[1]))


def _soft_step(s: np.ndarray, eps: float) -> np.ndarray:
    return 0.5 + np.arctan(s / eps) / np.pi


def _soft_box(u, v, b, eps) -> np.ndarray:
    return (
        _soft_step(u - b[0], eps) * _soft_step(b[1] - u, eps)
        * _soft_step(v - b[2], eps) * _soft_step(b[3] - v, eps)
    )  # fmt: skip


# Each family's parameters after the box, and the notches they cut, in the frame where
# the family's notches lie where Prior.wings expects them.
def _notches(family: str, box4: np.ndarray, q: np.ndarray) -> list[np.ndarray]:
    u0, u1, v0, v1 = box4
    if family == "rect":
        return []
    if family == "L":  # q = (u extent, v extent) of the corner notch
        return [np.array([u0 - 1.0, u0 + q[0], v0 - 1.0, v0 + q[1]])]
    if family == "T":  # q = (stem u0, stem u1, depth)
        depth = v0 + q[2]
        return [np.array([u0 - 1.0, q[0], v0 - 1.0, depth]),
                np.array([q[1], u1 + 1.0, v0 - 1.0, depth])]  # fmt: skip
    if family == "U":  # q = (notch u0, notch u1, depth)
        return [np.array([q[0], q[1], v1 - q[2], v1 + 1.0])]
    return [np.array(q[:4])]  # courtyard: the hole


def prior_indicator(u, v, family: str, params: np.ndarray, eps: float) -> np.ndarray:
    """H_eps(phi~(T(x))): the prior's smoothed indicator at frame coordinates (u, v).

    params : box (u0, u1, v0, v1) then the family's notch parameters, metres."""
    b = params[:4]
    inside = _soft_box(u, v, b, eps)
    for n in _notches(family, b, params[4:]):
        inside = inside * (1.0 - _soft_box(u, v, n, eps))
    return inside


def prior_energy(
    segment: np.ndarray, indicator: np.ndarray, seen: np.ndarray | None = None
) -> float:
    """Eq. 4's data term of one prior over its domain: the mean of (H(phi) - H(phi~))^2
    normalised by the template's variance sigma^2 = mean(phi~^2) - mean(phi~)^2.

    ``seen`` (same shape, 0-1) weighs each cell by the share of it whose footprint the
    views show: a crown standing over a roof's corner hides whether the roof goes on
    under it, so there the prior is neither paid for covering it nor for leaving it out
    (both means over the seen cells: a prior grown into the hidden cells gains no
    variance either)."""
    if seen is None:
        return float(np.mean((segment - indicator) ** 2) / max(_variance(indicator), 1e-6))
    w = seen / max(float(seen.sum()), 1e-9)
    mismatch = float(np.sum(w * (segment - indicator) ** 2))
    mean = float(np.sum(w * indicator))
    return mismatch / max(float(np.sum(w * indicator**2)) - mean**2, 1e-6)


@dataclass
class SegmentFrame:
    """A segment's cells on the registration grid, in a frame of its main direction.

    mask : (h, w) float 0/1; u, v : (h, w) frame coordinates of the cells, metres;
    theta, origin : the frame; step : cell size, metres; seen : (h, w) float 0-1, the
    share of each cell whose footprint the views show (None: all of every cell)."""

    mask: np.ndarray
    u: np.ndarray
    v: np.ndarray
    theta: float
    origin: np.ndarray
    step: float
    seen: np.ndarray | None = None


def segment_frame(
    mask: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    gsd: float,
    hidden: np.ndarray | None = None,
) -> SegmentFrame:
    """The frame of a segment: its centroid, its main direction (the outline's edges,
    modulo 90 degrees), its cells pooled to the registration grid.

    mask : (h, w) bool crop with a margin; xs : (w,) and ys : (h,) cell centres, metres;
    hidden : (h, w) bool, optional, cells off the segment whose footprint no view shows
    (a crown over the roof's edge): :func:`prior_energy` leaves them out."""
    k = max(1, int(round(_REGISTRATION_GSD / gsd)))
    h, w = (mask.shape[0] // k) * k, (mask.shape[1] // k) * k
    pooled = mask[:h, :w].reshape(h // k, k, w // k, k).mean(axis=(1, 3))
    seen = None
    if hidden is not None and hidden.any():
        seen = 1.0 - hidden[:h, :w].reshape(h // k, k, w // k, k).mean(axis=(1, 3))
    cx = xs[:w].reshape(-1, k).mean(axis=1)
    cy = ys[:h].reshape(-1, k).mean(axis=1)
    X, Y = np.meshgrid(cx, cy)
    weight = pooled.sum()
    origin = np.array([(X * pooled).sum() / weight, (Y * pooled).sum() / weight])
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL,
                                   cv2.CHAIN_APPROX_SIMPLE)  # fmt: skip
    rings = []
    for c in contours:
        # a side at a slant is a staircase of cells, whose edges' mean direction is pulled
        # towards the grid's (seeds 0-2: 13 of 75 segments over 3 degrees off, one 14);
        # Douglas-Peucker within the sides' own jog, two cells, keeps the sides' chords
        # (2 of 75 over 3 degrees, mean error 1.8 -> 0.7 degrees)
        c = cv2.approxPolyDP(c, _JOG_CELLS, True)[:, 0, :].astype(np.float64)
        if len(c) >= 3:
            ring = np.column_stack([xs[0] + c[:, 0] * gsd, ys[0] - c[:, 1] * gsd])
            rings.append(np.vstack([ring, ring[:1]]))
    theta = dominant_direction(rings, max_jog=_JOG_CELLS * gsd) if rings else 0.0
    dx, dy = X - origin[0], Y - origin[1]
    c, s = np.cos(theta), np.sin(theta)
    return SegmentFrame(pooled, c * dx + s * dy, -s * dx + c * dy, theta, origin, k * gsd,
                        seen)  # fmt: skip


def _rotated(frame: SegmentFrame, quarter: int) -> SegmentFrame:
    """The same frame turned by ``quarter`` * 90 degrees."""
    c, s = np.cos(quarter * np.pi / 2), np.sin(quarter * np.pi / 2)
    u, v = c * frame.u + s * frame.v, -s * frame.u + c * frame.v
    return SegmentFrame(frame.mask, u, v, frame.theta + quarter * np.pi / 2, frame.origin,
                        frame.step, frame.seen)  # fmt: skip


def _initial_params(frame: SegmentFrame, family: str, min_part: float) -> np.ndarray | None:
    """A pose read off the segment: its extent, and the notch its bounding box leaves where
    the family has one; None when the box leaves no such notch."""
    inside = frame.mask > 0.5
    u, v = frame.u[inside], frame.v[inside]
    if len(u) < 4:
        return None
    b = (
        np.array([u.min(), u.max(), v.min(), v.max()])
        + np.array([-0.5, 0.5, -0.5, 0.5]) * frame.step
    )
    if family == "rect":
        return b
    empty = ~inside & (frame.u > b[0]) & (frame.u < b[1]) & (frame.v > b[2]) & (frame.v < b[3])
    # an opening narrower than any arm parts a notch from the slivers the segment's
    # rounded corners leave, which would otherwise join it and touch the wrong sides; a
    # U's notch and a courtyard's hole are ground, not arms, and may be narrower than
    # that opening: for them the opening narrows until it leaves one
    widest = int(np.ceil(0.5 * min_part / frame.step)) - 1
    radii = range(widest, -1, -1) if family in ("U", "courtyard") else [widest]
    for r in radii:
        opened = empty if r == 0 else ndimage.binary_opening(empty, np.ones((3, 3), bool),
                                                              iterations=r)  # fmt: skip
        q = _notch_read(frame, family, b, opened, min_part)
        if q is not None:
            return np.concatenate([b, q])
    return None


def _notch_read(
    frame: SegmentFrame, family: str, b: np.ndarray, empty: np.ndarray, min_part: float
) -> np.ndarray | None:
    """The family's notch parameters read off the largest empty component of the box that
    touches the sides where the family has its notch; None when none is min_part^2 large."""
    labels, n = ndimage.label(empty)
    best, best_cells = None, 0
    for k in range(1, n + 1):
        cells = labels == k
        cu, cv = frame.u[cells], frame.v[cells]
        ext = np.array([cu.min(), cu.max(), cv.min(), cv.max()])
        near = np.abs(ext - b) < 1.5 * frame.step  # which sides of the box it touches
        if family == "L" and near[0] and near[2] and not near[1] and not near[3]:
            q = np.array([ext[1] - b[0], ext[3] - b[2]])
        elif (family == "U" and near[3] and not (near[0] or near[1] or near[2])
              and b[3] - ext[2] >= min_part - frame.step
              and _mouth(frame, cells, b[3]) >= min(min_part, 0.5 * (ext[1] - ext[0]))
              ):  # fmt: skip
            # a dent shallower than the arms are long is not a U's notch, nor a hole that
            # a slit through a thin side joins to the outside: a U's notch opens onto its
            # side over half its width, or an arm's width (an L's notch, whose far side a
            # rounded tip closes, opens over less than half)
            q = np.array([ext[0], ext[1], b[3] - ext[2]])
        elif family == "courtyard" and not near.any():
            q = ext.copy()
        elif family == "T" and near[0] and near[2] and not near[1] and not near[3]:
            other = [j for j in range(1, n + 1) if j != k]
            right = [j for j in other if abs(frame.u[labels == j].max() - b[1]) < 1.5 * frame.step
                     and abs(frame.v[labels == j].min() - b[2]) < 1.5 * frame.step]  # fmt: skip
            if right:
                r = labels == right[0]
                q = np.array([ext[1], frame.u[r].min(), 0.5 * (ext[3] + frame.v[r].max()) - b[2]])
            else:  # the other notch too shallow to read: start it one arm wide
                q = np.array([ext[1], b[1] - min_part, ext[3] - b[2]])
        else:
            continue
        if cells.sum() > best_cells:
            best, best_cells = q, cells.sum()
    if best is None or best_cells * frame.step**2 < min_part**2:
        return None
    return best


def _mouth(frame: SegmentFrame, cells: np.ndarray, v1: float) -> float:
    """The extent along u, metres, of ``cells`` within a cell and a half of the box's side
    at v = ``v1``: where an empty component opens onto that side."""
    at_side = cells & (frame.v > v1 - 1.5 * frame.step)
    if not at_side.any():
        return 0.0
    u = frame.u[at_side]
    return float(u.max() - u.min()) + frame.step


def _feasible(family: str, p: np.ndarray, min_part: float) -> bool:
    u0, u1, v0, v1 = p[:4]
    if u1 - u0 < min_part or v1 - v0 < min_part:
        return False
    q = p[4:]
    if family == "L":
        return min_part <= q[0] <= u1 - u0 - min_part and min_part <= q[1] <= v1 - v0 - min_part
    # the arms are parts, at least min_part wide and (a U's, beyond its base) long; a U's
    # notch and a courtyard's hole are ground, of any width
    if family == "T":
        a, b, depth = q
        return (a - u0 >= min_part and u1 - b >= min_part and b - a >= min_part
                and min_part <= depth <= v1 - v0 - min_part)  # fmt: skip
    if family == "U":
        a, b, depth = q
        return (a - u0 >= min_part and u1 - b >= min_part and b > a
                and min_part <= depth <= v1 - v0 - min_part)  # fmt: skip
    if family == "courtyard":
        a, b, c, d = q
        return (a - u0 >= min_part and u1 - b >= min_part and c - v0 >= min_part
                and v1 - d >= min_part and b > a and d > c)  # fmt: skip
    return True


def _projected(family: str, p: np.ndarray, min_part: float, gap: float) -> np.ndarray | None:
    """The nearest pose to ``p`` whose notches leave every arm ``min_part`` wide (a
    segment's ragged edge can make a notch read off it a little too deep) and a U's notch
    or a courtyard's hole at least ``gap`` wide; None when the box itself is too small for
    the family."""
    p = p.copy()
    u0, u1, v0, v1 = p[:4]
    if u1 - u0 < min_part or v1 - v0 < min_part:
        return None
    if family == "L":
        if min(u1 - u0, v1 - v0) < 2 * min_part:
            return None
        p[4] = np.clip(p[4], min_part, u1 - u0 - min_part)
        p[5] = np.clip(p[5], min_part, v1 - v0 - min_part)
    elif family == "T":
        if u1 - u0 < 3 * min_part or v1 - v0 < 2 * min_part:
            return None
        p[4] = np.clip(p[4], u0 + min_part, u1 - 2 * min_part)
        p[5] = np.clip(p[5], p[4] + min_part, u1 - min_part)
        p[6] = np.clip(p[6], min_part, v1 - v0 - min_part)
    elif family == "U":
        if u1 - u0 < 2 * min_part + gap or v1 - v0 < 2 * min_part:
            return None
        p[4] = np.clip(p[4], u0 + min_part, u1 - min_part - gap)
        p[5] = np.clip(p[5], p[4] + gap, u1 - min_part)
        p[6] = np.clip(p[6], min_part, v1 - v0 - min_part)
    elif family == "courtyard":
        if min(u1 - u0, v1 - v0) < 2 * min_part + gap:
            return None
        p[4] = np.clip(p[4], u0 + min_part, u1 - min_part - gap)
        p[5] = np.clip(p[5], p[4] + gap, u1 - min_part)
        p[6] = np.clip(p[6], v0 + min_part, v1 - min_part - gap)
        p[7] = np.clip(p[7], p[6] + gap, v1 - min_part)
    return p


def register_prior(frame: SegmentFrame, family: str, min_part: float) -> Prior | None:
    """Eq. 2: the pose and notch sizes of ``family`` that best match the segment, over the
    four quarter turns of its frame; None when the segment leaves no place for the
    family's notch or no feasible pose fits."""
    best: Prior | None = None
    eps = _EPS_CELLS * frame.step
    for quarter in range(4 if family != "rect" and family != "courtyard" else 1):
        f = _rotated(frame, quarter)
        x0 = _initial_params(f, family, min_part)
        x0 = None if x0 is None else _projected(family, x0, min_part, f.step)
        if x0 is None or not _feasible(family, x0, min_part):
            continue
        evaluations = 0
        # the rotation joins the box and notches as an arc length at the box's half
        # diagonal, metres, so that one tolerance suits every parameter
        radius = 0.5 * float(np.hypot(x0[1] - x0[0], x0[3] - x0[2]))
        # the box stays within the domain: beyond it, where no cell is, growing is free
        reach = float(np.hypot(f.u, f.v).max()) + f.step

        def energy(p, f=f, radius=radius, reach=reach):
            nonlocal evaluations
            evaluations += 1
            if (not _feasible(family, p[1:], min_part) or abs(p[0]) > 0.25 * radius
                    or np.abs(p[1:5]).max() > reach):  # fmt: skip
                return 1e6
            c, s = np.cos(p[0] / radius), np.sin(p[0] / radius)
            u, v = c * f.u + s * f.v, -s * f.u + c * f.v
            return prior_energy(f.mask, prior_indicator(u, v, family, p[1:], eps), f.seen)

        start = np.concatenate([[0.0], x0])
        res = optimize.minimize(energy, start, method="Powell",
                                options={"maxfev": _MAX_EVALUATIONS, "xtol": 0.05 * f.step,
                                         "ftol": 1e-4})  # fmt: skip
        p = res.x if res.fun <= energy(start) else start
        e = energy(p)
        if best is None or e < best.energy:
            b = p[1:5]
            notches = [n.copy() for n in _notches(family, b, p[5:])]
            best = Prior(family, f.theta + p[0] / radius, f.origin, b.copy(), notches, e,
                         evaluations)  # fmt: skip
    return best


def compete_priors(
    frame: SegmentFrame, families: tuple[str, ...], min_part: float, lambda_: float
) -> tuple[Prior | None, dict]:
    """Eq. 4 over one segment: each family registered, the smallest normalised energy
    wins (the simpler family on a tie within 2 %), unless the unknown-object label
    (lambda^2 per segment cell) costs less. Returns the winner (None: unknown) and every
    family's energy."""
    best, energies = best_prior(frame, families, min_part)
    return unknown_or(best, frame, lambda_, energies), energies


def unknown_or(best: Prior | None, frame: SegmentFrame, lambda_: float, energies: dict):
    """``best`` unless the unknown-object label (lambda^2 per segment cell) costs less,
    then None; adds the unknown label's energy to ``energies``. Both over the cells
    whose footprint the views show (:func:`prior_energy`)."""
    if frame.seen is None:
        share = float(frame.mask.mean())
    else:
        share = float(np.sum(frame.mask * frame.seen) / max(float(frame.seen.sum()), 1e-9))
    unknown = lambda_**2 * share
    if np.isfinite(unknown):  # an infinite lambda: the segment is known to be a building
        energies["unknown"] = round(unknown, 5)
    return None if best is None or best.energy > unknown else best


def best_prior(
    frame: SegmentFrame, families: tuple[str, ...], min_part: float
) -> tuple[Prior | None, dict]:
    """Eq. 2 for every family: the smallest normalised energy (the simpler family on a tie
    within 2 %), and every family's energy."""
    energies, best = {}, None
    for family in families:
        p = register_prior(frame, family, min_part)
        if p is None:
            continue
        energies[family] = round(float(p.energy), 5)
        if best is None or p.energy < 0.98 * best.energy:
            best = p
    return best, energies


def label_count(segments: int) -> tuple[int, int]:
    """k = ceil(log2(1 + q)) labelling dimensions for q segments, and nu = 2^k regions."""
    k = int(np.ceil(np.log2(1 + segments))) if segments > 0 else 0
    return k, 2**k


def leftover_parts(
    segment: np.ndarray,
    prior: np.ndarray,
    var: float,
    lambda_: float,
    rho: float,
    min_cells: int,
) -> list[np.ndarray]:
    """Eq. 4's labelling inside one segment for a fixed prior: each cell takes the prior's
    label (cost 1/sigma^2 where the prior misses it) or the unknown label (cost lambda^2),
    with rho times the boundary between them; one graph cut on the 4-neighbour grid.
    Returns the connected parts of the segment left unknown that are at least
    ``min_cells`` large (boolean masks).

    segment, prior : (h, w) bool (the prior's outline rasterised on the same cells)."""
    cells = segment.ravel()
    if not cells.any():
        return []
    missed = (segment & ~prior).ravel().astype(np.float64)
    unary = np.column_stack([missed / max(var, 1e-6), np.full(len(cells), lambda_**2)])
    unary[~cells] = [0.0, 1e6]  # outside the segment: not a part
    h, w = segment.shape
    idx = np.arange(h * w).reshape(h, w)
    edges = np.concatenate([
        np.column_stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()]),
        np.column_stack([idx[:-1, :].ravel(), idx[1:, :].ravel()]),
    ])  # fmt: skip
    labels = binary_cut(unary, edges, np.ones(len(edges)), rho).reshape(h, w)
    unknown = (labels == 1) & segment
    parts, n = ndimage.label(unknown)
    sizes = np.bincount(parts.ravel(), minlength=n + 1)
    return [parts == k for k in range(1, n + 1) if sizes[k] >= min_cells]


def union_outline(priors: list[Prior]) -> Polygon:
    """The building's outline: the union of its parts' priors."""
    return unary_union([p.polygon() for p in priors])


def decompose_outline(
    mask: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    grid: Grid,
    families: tuple[str, ...],
    min_part: float,
    lambda_: float,
    rho: float,
    min_cells: int,
    max_parts: int = 4,
    lambda_label: float | None = None,
    hidden: np.ndarray | None = None,
) -> tuple[list[Prior], dict]:
    """Eq. 4 on one segment: the winning prior, then priors for the parts its labelling
    leaves to the data term, up to ``max_parts`` priors. Returns the priors (none: the
    unknown label won) and the first competition's energies.

    mask : (h, w) bool on ``grid``; xs : (w,), ys : (h,) its cell centres, metres;
    lambda_ : the unknown label's cost in the competition (infinite: the segment is a
    building); lambda_label : its cost in the labelling of the leftover parts (default
    ``lambda_``); rho : the labelling's boundary weight; min_cells : smallest part;
    hidden : (h, w) bool, optional, cells off the segment whose footprint no view shows
    (:func:`prior_energy`)."""
    gsd = grid.gsd
    label_cost = lambda_ if lambda_label is None else lambda_label
    frame = segment_frame(mask, xs, ys, gsd, hidden)
    best, energies = best_prior(frame, families, min_part)
    if best is not None and frame.seen is not None:
        covered = rasterize_on(best.polygon(), grid)
        if (covered & hidden).sum() > MAX_HIDDEN_SHARE * covered.sum():
            # mostly what no view shows: the hidden cells are ground to it, as to a prior
            # without them
            hidden = None
            frame = segment_frame(mask, xs, ys, gsd)
            best, energies = best_prior(frame, families, min_part)
    first = unknown_or(best, frame, lambda_, energies)
    if first is None:
        # eq. 4's labelling gives the unknown label what no prior explains: a crown the
        # segmentation took in beside a roof would otherwise cost the best prior its
        # whole segment (a T of 336 m2 with a crown's edge on it, left out on a seed
        # beyond the tuning ones). The priors compete once more on what it leaves them.
        if best is None:
            return [], energies
        covered = rasterize_on(best.polygon(), grid)
        parts = leftover_parts(mask, covered, _variance(covered), label_cost, rho, min_cells)
        if not parts:
            return [], energies
        mask = mask & ~np.any(parts, axis=0)
        first, again = compete_priors(segment_frame(mask, xs, ys, gsd, hidden), families,
                                      min_part, lambda_)  # fmt: skip
        energies = {**energies, "without_unknown_parts": again}
        if first is None:
            return [], energies
    priors = [first]
    covered = rasterize_on(first.polygon(), grid)
    for part in leftover_parts(mask, covered, _variance(covered), label_cost, rho, min_cells):
        p, _ = compete_priors(segment_frame(part, xs, ys, gsd), families, min_part, lambda_)
        if p is not None and len(priors) < max_parts:
            priors.append(p)
    return priors, energies


def crowns_over_the_edge(mask, tree, dsm, gsd: float, touch_m: float = 1.0) -> np.ndarray:
    """(h, w) bool the crowns beside the segment ``mask`` that could hide its roof: the
    fusion's ``tree`` cells off the segment, in parts that come within ``touch_m`` of
    it, where the DSM stands above the segment's lowest roof (its 5th percentile, the
    eaves: a crown under them hides no roof). Whether the roof goes on under them the
    views cannot tell: a square pyramid with a taller crown over its corner registered
    as an L (dev seeds 13 and 14).

    mask, tree : (h, w) bool; dsm : (h, w) metres, NaN unknown; gsd : metres per cell.
    The answer is :func:`decompose_outline`'s ``hidden``."""
    roof = dsm[mask & np.isfinite(dsm)]
    if not len(roof) or not (tree & ~mask).any():
        return np.zeros(mask.shape, bool)
    above = tree & ~mask & (np.nan_to_num(dsm, nan=-np.inf) > np.percentile(roof, 5))
    labels, _ = ndimage.label(above)
    near = ndimage.binary_dilation(mask, iterations=max(1, int(round(touch_m / gsd))))
    touching = np.unique(labels[near & above])
    return np.isin(labels, touching[touching > 0])


def _variance(indicator: np.ndarray) -> float:
    """sigma^2 of a template's indicator over its domain (eq. 4's normalisation)."""
    ind = np.asarray(indicator, np.float64)
    return float(np.mean(ind**2) - np.mean(ind) ** 2)


def rasterize_on(geom, grid: Grid) -> np.ndarray:
    """(h, w) bool cells of ``grid`` whose centre ``geom`` covers."""
    if geom.is_empty:
        return np.zeros(grid.shape, bool)
    return rasterio.features.rasterize([(geom, 1)], out_shape=grid.shape,
                                       transform=grid.transform, fill=0,
                                       dtype=np.uint8).astype(bool)  # fmt: skip
