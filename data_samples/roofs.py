"""Roof faces of one rectangular wing, for each roof type of the synthetic city.

A wing is a rectangle with centre ``(cx, cy)``, half-length ``a`` along its axis
(the ridge direction, at ``angle`` radians from east) and half-width ``b``. Each
roof type is a list of planar faces, each a convex polygon with 3D vertices in
world coordinates; :func:`modeling.shared.roof_envelope.building_mesh` takes the upper
envelope of the faces of all wings of a building.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from modeling.shared.roof_envelope import RoofFace

ROOF_TYPES = ("flat", "shed", "gable", "hipped", "pyramid", "mansard", "multi-level")


@dataclass(frozen=True)
class Wing:
    """A rectangular part of a building footprint.

    Attributes
    ----------
    cx, cy : float
        Centre, world metres.
    a, b : float
        Half-length along the axis and half-width across it, metres (a >= b for ridges).
    angle : float
        Axis direction, radians counter-clockwise from east.
    """

    cx: float
    cy: float
    a: float
    b: float
    angle: float

    def to_world(self, s: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Local (along, across) coordinates to world x, y."""
        c, si = np.cos(self.angle), np.sin(self.angle)
        return self.cx + c * s - si * r, self.cy + si * s + c * r

    def corners(self) -> np.ndarray:
        """(4, 2) world corners, counter-clockwise."""
        s = np.array([-self.a, self.a, self.a, -self.a])
        r = np.array([-self.b, -self.b, self.b, self.b])
        return np.column_stack(self.to_world(s, r))


def _face(wing: Wing, local: list[tuple[float, float, float]]) -> RoofFace:
    pts = np.asarray(local, dtype=np.float64)
    x, y = wing.to_world(pts[:, 0], pts[:, 1])
    A = np.column_stack([x, y, np.ones(len(x))])
    plane, *_ = np.linalg.lstsq(A, pts[:, 2], rcond=None)
    xy = np.column_stack([x, y])
    if _signed_area(xy) < 0:
        xy = xy[::-1]
    return RoofFace(xy, plane)


def _signed_area(xy: np.ndarray) -> float:
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def wing_roof_faces(
    wing: Wing, roof_type: str, eave: float, *, pitch_deg: float = 35.0, tiers=()
) -> list[RoofFace]:
    """The roof faces of one wing.

    Parameters
    ----------
    wing : Wing
    roof_type : str
        One of :data:`ROOF_TYPES`.
    eave : float
        Absolute eave height (top of the walls), metres.
    pitch_deg : float
        Roof slope in degrees (the lower, steep slope for a mansard is 70 degrees and
        this is the slope of its upper part).
    tiers : sequence of (Wing, height)
        For ``multi-level``: the upper flat tiers (absolute heights), each a wing inside
        this one.

    Returns
    -------
    list of RoofFace
    """
    a, b = wing.a, wing.b
    tp = np.tan(np.radians(pitch_deg))
    if roof_type in ("flat", "multi-level"):
        faces = [_face(wing, [(-a, -b, eave), (a, -b, eave), (a, b, eave), (-a, b, eave)])]
        for tier, h in tiers:
            ta, tb = tier.a, tier.b
            faces.append(_face(tier, [(-ta, -tb, h), (ta, -tb, h), (ta, tb, h), (-ta, tb, h)]))
        return faces
    if roof_type == "shed":
        top = eave + 2 * b * tp
        return [_face(wing, [(-a, -b, eave), (a, -b, eave), (a, b, top), (-a, b, top)])]
    ridge = eave + b * tp
    if roof_type == "gable":
        return [
            _face(wing, [(-a, -b, eave), (a, -b, eave), (a, 0, ridge), (-a, 0, ridge)]),
            _face(wing, [(-a, 0, ridge), (a, 0, ridge), (a, b, eave), (-a, b, eave)]),
        ]
    if roof_type == "hipped":
        h = a - b
        if h <= 1e-6:
            return wing_roof_faces(wing, "pyramid", eave, pitch_deg=pitch_deg)
        return [
            _face(wing, [(-a, -b, eave), (a, -b, eave), (h, 0, ridge), (-h, 0, ridge)]),
            _face(wing, [(a, -b, eave), (a, b, eave), (h, 0, ridge)]),
            _face(wing, [(a, b, eave), (-a, b, eave), (-h, 0, ridge), (h, 0, ridge)]),
            _face(wing, [(-a, b, eave), (-a, -b, eave), (-h, 0, ridge)]),
        ]
    if roof_type == "pyramid":
        apex = eave + min(a, b) * tp
        c = [(-a, -b), (a, -b), (a, b), (-a, b)]
        return [
            _face(wing, [(*c[i], eave), (*c[(i + 1) % 4], eave), (0.0, 0.0, apex)])
            for i in range(4)
        ]
    if roof_type == "mansard":
        inset = min(0.3 * b, 2.0)
        break_z = eave + inset * np.tan(np.radians(70.0))
        ia, ib = a - inset, b - inset
        top = break_z + min(ib, 1.5) * tp * 0.3
        outer = [(-a, -b), (a, -b), (a, b), (-a, b)]
        inner = [(-ia, -ib), (ia, -ib), (ia, ib), (-ia, ib)]
        faces = [
            _face(
                wing,
                [
                    (*outer[i], eave),
                    (*outer[(i + 1) % 4], eave),
                    (*inner[(i + 1) % 4], break_z),
                    (*inner[i], break_z),
                ],
            )
            for i in range(4)
        ]
        upper = Wing(wing.cx, wing.cy, ia, ib, wing.angle)
        rid = np.degrees(np.arctan2(top - break_z, ib))
        faces += wing_roof_faces(upper, "hipped", break_z, pitch_deg=float(rid))
        return faces
    raise ValueError(f"unknown roof type {roof_type!r}")
