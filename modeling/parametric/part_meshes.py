"""Meshes (step 4): each wing's roof planes clipped to its rectangle, the wings of a
building joined by the upper envelope of their roofs, walls down to the ground.

A wing's roof is the minimum of affine functions of (u, v) (eq. 5's planes with vertical
ends dropped, and a cap), so the region where each plane is the lowest is the wing's
rectangle clipped by half-planes: a convex polygon. The wings of a building overlap
(an L's corner) and stand on one another (a tier); the envelope mesher
(:func:`modeling.shared.roof_envelope.building_solid`) nodes their faces into one closed,
outward-oriented solid.
"""

from __future__ import annotations

import numpy as np

from modeling.shared.roof_envelope import RoofFace, lowest_plane_faces

from .roof_geometry import RoofFit, eave_shifts


def wing_planes(wing: np.ndarray, fit: RoofFit) -> list[np.ndarray]:
    """The wing's roof as affine functions z = a u + b v + c of its frame: (3,) each."""
    u0, u1, v0, v1 = wing
    t = fit.snapped()
    z = fit.z_main
    e = eave_shifts(fit.offset)  # plane k: tan(omega_k) (d_k + e_k) above P_m
    sides = (np.array([1.0, 0.0, e[0] - u0]), np.array([0.0, 1.0, e[1] - v0]),
             np.array([-1.0, 0.0, u1 + e[2]]), np.array([0.0, -1.0, v1 + e[3]]))  # fmt: skip
    planes = [tk * side + np.array([0.0, 0.0, z])
              for tk, side in zip(t, sides, strict=True) if np.isfinite(tk)]  # fmt: skip
    if fit.cap is not None or not planes:
        planes.append(np.array([0.0, 0.0, z + (fit.cap or 0.0)]))
    return planes


def wing_faces(wing: np.ndarray, fit: RoofFit, theta: float, origin: np.ndarray) -> list[RoofFace]:
    """The wing's roof faces in world coordinates: for each plane, the part of the
    rectangle where it is the lowest."""
    u0, u1, v0, v1 = wing
    rect = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]], dtype=np.float64)
    return lowest_plane_faces(rect, np.asarray(wing_planes(wing, fit)), theta, origin)
