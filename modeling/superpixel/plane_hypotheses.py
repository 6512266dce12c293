"""RANSAC roof-plane hypotheses per super-pixel (the super-pixel paper, section 5.1)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.planes import ransac_planes
from workbench.raster import Grid

from .options import SuperpixelOptions


@dataclass
class SuperpixelPoints:
    """The DSM points of every super-pixel: ``points[starts[i]:ends[i]]`` (world metres)."""

    points: np.ndarray
    starts: np.ndarray
    ends: np.ndarray

    def of(self, i: int) -> np.ndarray:
        return self.points[self.starts[i] : self.ends[i]]


def superpixel_points(
    labels: np.ndarray, dsm: np.ndarray, grid: Grid, wanted: np.ndarray | None = None
) -> SuperpixelPoints:
    """Group the DSM's known cells, as 3D points, by super-pixel.

    Parameters
    ----------
    labels : (H, W) int
        Super-pixels 0..N-1.
    dsm : (H, W) float
        Metres, NaN unknown.
    grid : Grid
    wanted : (N,) bool, optional
        The super-pixels whose points are kept (the others get none): a city's buildings
        cover a third of its cells.
    """
    known = np.isfinite(dsm)
    if wanted is not None:
        known &= wanted[labels]
    rows, cols = np.nonzero(known)  # raster order, kept within each super-pixel
    lab = labels[rows, cols]
    order = np.argsort(lab, kind="stable")
    rows, cols, lab = rows[order], cols[order], lab[order]
    x, y = grid.cell_center(rows, cols)
    n = int(labels.max()) + 1
    return SuperpixelPoints(
        np.column_stack([x, y, dsm[rows, cols]]), np.searchsorted(lab, np.arange(n)),
        np.searchsorted(lab, np.arange(n), side="right"),
    )  # fmt: skip


def plane_hypotheses(
    members: np.ndarray,
    pts: SuperpixelPoints,
    adjacency: dict[int, list[int]],
    options: SuperpixelOptions,
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """A RANSAC plane for each super-pixel of a building (section 5.1).

    Super-pixels with at least ``min_plane_points`` heights get a plane of their own. One
    with fewer, none of whose neighbours has a plane, borrows its neighbours' heights,
    ring by ring (two rings at most): on coarse rasters, such as LiDAR at its point
    spacing, whole roof sides are made of such super-pixels and would otherwise get no
    hypothesis at all.

    Parameters
    ----------
    adjacency : {super-pixel: adjacent super-pixels}

    Returns
    -------
    {super-pixel: (plane (4,), the points it was fitted to (N, 3))} for the super-pixels
    with enough points and a roof-like plane.
    """
    inside = set(int(i) for i in members)
    enough = (pts.ends[members] - pts.starts[members]) >= options.min_plane_points
    own = [int(i) for i in members[enough]]
    out = _fit(own, [pts.of(i) for i in own], options)
    small = [int(i) for i in members[~enough]]
    borrowing, groups = [], []
    for i in small:
        if any(k in out for k in adjacency.get(i, ())):
            continue  # a neighbour's plane can stand for it
        group, ring = {i}, {i}
        for _ in range(2):
            ring = {k for j in ring for k in adjacency.get(j, ()) if k in inside} - group
            group |= ring
            if sum(len(pts.of(j)) for j in group) >= options.min_plane_points:
                break
        borrowing.append(i)
        groups.append(np.concatenate([pts.of(j) for j in sorted(group)]))
    out.update(_fit(borrowing, groups, options))
    return out


def _fit(
    ids: list[int], point_sets: list[np.ndarray], options: SuperpixelOptions
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """{id: (plane, its points)} of the point sets with a roof-like RANSAC plane."""
    planes = ransac_planes(
        point_sets, options.ransac_threshold_m, options.ransac_iterations, seed=options.seed
    )
    return {
        i: (plane, points)
        for i, plane, points in zip(ids, planes, point_sets, strict=True)
        if np.isfinite(plane[0])
    }
