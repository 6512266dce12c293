"""Sloped roof faces the mesh lost into a hole, run on down to their eaves (not in the
paper; it uses the paper's z-symmetric roof planes, section 5.3).

A mesh has no surface where no view saw one. At a survey's edge the views look from one
side only: a roof face that slopes away from them is seen down to some row, and beyond it
the hole runs on over the rest of the face, the wall and the ground, so that the outline
(:func:`~.labelling.fill_holes`: a hole that reaches the ground is ground) stops where the
face was last seen, inside the wall. A sloped face does not end in mid-air: it runs down
to its eaves, and a gabled or hipped roof's z-symmetric faces have their eaves level. So
where a face was last seen above the lowest cell seen on its twin, the cells beyond it,
downhill, on which its plane still stands above that height are its own.

What bounds it, measured on the mesh fusions of ``small`` seeds 0-2 (cells taken of the
building's own that the hole took, against cells of none or another; with every bound,
124 and 3):

- each face's eaves are its own twin's: the lowest cell seen on any paired face of the
  building gave 485 and 4049 (a U-shaped building's faces ran on past their walls into
  the hidden ground at their feet, down to a steeper lower face's eaves);
- faces of 15 to 45 degrees: a flatter plane's fit error is metres of reach, and a 52
  degree plane across a 48 m tower's rounded wall, paired with one on its podium, ran
  1270 cells on;
- a face seen over at least half its fall to its eaves: without it, 1811 cells of
  planes a few cells wide where a wall's top rounds off through a face's pitch (a shed
  roof's high wall, at its twin's);
- across the width the face was seen over: a gable's face keeps it down to the eaves;
  a hipped face widens, and its lower corners beyond it are left to the hips' faces.

The mesh rounds each eave off its plane, so the twin's lowest seen cell stands above
the eaves and a face gets back less than it lost: seed 2's hipped roof at the survey's
edge gets none of its 148 lost cells (its east face was seen down to 0.35 m above its
twin's lowest cell, the cells it lost reach lower). A mansard's steep lower faces and a
shed roof have no twin seen, and are not run on.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .shapes import on_plane, z_symmetric

MIN_TILT_DEG = 15.0  # flatter faces are not run on: a degree of fit error is metres of reach
MAX_TILT_DEG = 45.0  # steeper planes are as often a mesh's rounded wall tops as roof faces


def faces_to_eaves(
    mask: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    planes: np.ndarray,
    blocked: np.ndarray,
    angle_deg: float,
    inlier_m: float,
    gsd: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The unknown cells beyond each sloped face's last seen cells on which its plane
    stands above its eaves: the cells to join the outline, and the plane's heights there.

    A seen cell is on a plane as :func:`~.shapes.roof_planes` counts it
    (:func:`~.shapes.on_plane`); the faces are the planes of
    :data:`MIN_TILT_DEG` to :data:`MAX_TILT_DEG`. A face's eaves stand at the lowest
    cell on its twin, the face of z-symmetric normal whose highest cell is nearest its
    own (the ridge they share); a face seen over less than half its fall to them is
    not run on. Its last seen cells are its cells within two cells (by their sides) of
    an unknown cell (outside ``mask`` or in it: the hidden cells the outline has taken
    in already), as a mesh's cells before a hole stray off the plane. An unknown cell
    outside ``mask`` is the face's when it lies downhill of the nearest of them, within
    the face's seen cells' extent across the downhill direction, the plane stands there
    at the eaves' height or above, and it reaches the building through such cells; a
    cell two faces claim takes the higher.

    Parameters
    ----------
    mask : (h, w) bool
        The building's outline cells.
    points : (h, w, 3) float
        Each cell as a point: x, y (metres) and its DSM height, NaN unknown.
    normals : (3, h, w) float
        Unit normals, NaN unknown.
    planes : (P, 4) float
        The building's roof planes (n, d): n . X + d = 0, unit n with n_z > 0.
    blocked : (h, w) bool
        Cells not to take (another building's).
    angle_deg, inlier_m : float
        A cell's membership of a plane, as :func:`~.shapes.roof_planes`.
    gsd : float
        The cells' size, metres.

    Returns
    -------
    run_on : (h, w) bool
    level : (h, w) float
        The plane's height on ``run_on`` cells, metres; NaN elsewhere.
    """
    run_on = np.zeros(mask.shape, bool)
    level = np.full(mask.shape, np.nan)
    z = points[..., 2]
    hole = ~np.isfinite(z) & ~mask & ~blocked
    tilt = np.degrees(np.arccos(np.clip(planes[:, 2], 0.0, 1.0)))
    sloped = np.flatnonzero((tilt >= MIN_TILT_DEG) & (tilt <= MAX_TILT_DEG))
    if len(sloped) < 2 or not hole.any():
        return run_on, level
    seen = mask & np.isfinite(z) & np.isfinite(normals).all(axis=0)
    X, Y = points[..., 0], points[..., 1]
    seen_points, seen_normals = points[seen], normals[:, seen].T
    cos_tol = np.cos(np.radians(angle_deg))
    on, low, top = {}, {}, {}
    for p in sloped:
        cells = np.zeros(mask.shape, bool)
        cells[seen] = on_plane(seen_points, seen_normals, planes[p], angle_deg, inlier_m)
        if cells.any():
            height = _plane_height(planes[p], X[cells], Y[cells])
            on[p], low[p], top[p] = cells, float(height.min()), float(height.max())
    # the face's last cells: before a hole, or before the unknown cells already in the
    # outline (its least rectangle's, the rim's); a mesh's last cells stray off the
    # plane: two cells by the sides
    beside_hole = ndimage.binary_dilation(~np.isfinite(z) & ~blocked, iterations=2)
    for p, cells in on.items():
        last = cells & beside_hole
        twins = [q for q in on if planes[q, :3] @ z_symmetric(planes[p, :3]) >= cos_tol]
        if not last.any() or not twins:
            continue
        eaves = low[min(twins, key=lambda q: abs(top[q] - top[p]))]
        # a face is run on no further than it was seen: a sliver of a wall's rounded
        # top, at a shed roof's twin's pitch, is no face
        if top[p] - low[p] < 0.5 * (top[p] - eaves):
            continue
        _, (ri, ci) = ndimage.distance_transform_edt(~last, return_indices=True)
        height = _plane_height(planes[p], X, Y)
        downhill = planes[p, :2] / np.hypot(planes[p, 0], planes[p, 1])  # z falls along it
        along = (X - X[ri, ci]) * downhill[0] + (Y - Y[ri, ci]) * downhill[1]
        across = Y * downhill[0] - X * downhill[1]
        width = across[cells]
        in_width = (across >= width.min() - gsd / 2) & (across <= width.max() + gsd / 2)
        ok = hole & (along > 0) & (height >= eaves) & in_width
        groups, _ = ndimage.label(ok | mask)
        mine = np.isin(groups, np.unique(groups[last])) & ok
        level = np.where(mine, np.fmax(level, height), level)
        run_on |= mine
    return run_on, level


def _plane_height(plane: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The plane's height (metres) over x, y: n . X + d = 0 solved for z."""
    return -(plane[0] * x + plane[1] * y + plane[3]) / plane[2]
