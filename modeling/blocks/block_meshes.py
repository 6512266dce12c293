"""Meshes (step 5): each block's roof faces on its support, the blocks of a building
merged into one closed, outward-oriented mesh down to the ground.

A block's roof is the minimum of affine functions (:mod:`.library`), so the part of its
support where one of them is the lowest is the support clipped by half-planes: a convex
polygon (:func:`modeling.shared.roof_envelope.lowest_plane_faces`). The faces of all
blocks go to the envelope mesher (:func:`modeling.shared.roof_envelope.building_solid`),
which walls the steps between blocks and down to the floor.
"""

from __future__ import annotations

import numpy as np
from shapely.geometry.polygon import orient

from modeling.shared.roof_envelope import RoofFace, lowest_plane_faces

from .library import Block, block_planes, ridge_frame
from .supports import Support


def frame_planes(block: Block, support: Support, ends) -> np.ndarray:
    """(P, 3) the block's planes as z = a u + b v + c of its support's frame."""
    L, W, joined = ridge_frame(support.frame, block.along, ends)
    planes = block_planes(block, L, W, joined)
    u0, _, v0, _ = support.frame.rect
    a, b, c = planes[:, 0], planes[:, 1], planes[:, 2]
    if block.along == 0:  # s = u - u0, t = v - v0
        return np.column_stack([a, b, c - a * u0 - b * v0])
    return np.column_stack([b, a, c - a * v0 - b * u0])  # s = v - v0, t = u - u0


def block_faces(block: Block, support: Support, ends) -> list[RoofFace]:
    """The block's roof faces in world coordinates: for each plane, the part of the
    support where it is the lowest."""
    fr = support.frame
    xy = np.asarray(orient(support.polygon, 1.0).exterior.coords)[:-1]
    u, v = fr.to_frame(xy[:, 0], xy[:, 1])
    return lowest_plane_faces(np.column_stack([u, v]), frame_planes(block, support, ends),
                              fr.theta, np.asarray(fr.origin))  # fmt: skip
