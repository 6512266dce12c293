"""RANSAC roof-plane hypotheses per super-pixel (the super-pixel paper, section 5.1)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workbench.planes import ransac_plane
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


def superpixel_points(labels: np.ndarray, dsm: np.ndarray, grid: Grid) -> SuperpixelPoints:
    """Group the DSM's known cells, as 3D points, by super-pixel."""
    X, Y = grid.cell_centers()
    ok = np.isfinite(dsm)
    lab = labels[ok]
    order = np.argsort(lab, kind="stable")
    pts = np.column_stack([X[ok], Y[ok], dsm[ok]])[order]
    n = int(labels.max()) + 1
    sl = lab[order]
    return SuperpixelPoints(
        pts, np.searchsorted(sl, np.arange(n)), np.searchsorted(sl, np.arange(n), side="right")
    )


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
    out = {}

    def fit(i: int, group: set[int]) -> None:
        points = np.concatenate([pts.of(j) for j in sorted(group)])
        plane = ransac_plane(
            points, options.ransac_threshold_m, options.ransac_iterations, seed=options.seed
        )
        if plane is not None:
            out[i] = (plane, points)

    small = []
    for i in map(int, members):
        if len(pts.of(i)) >= options.min_plane_points:
            fit(i, {i})
        else:
            small.append(i)
    own = set(out)
    for i in small:
        if any(k in own for k in adjacency.get(i, ())):
            continue  # a neighbour's plane can stand for it
        group, ring = {i}, {i}
        for _ in range(2):
            ring = {k for j in ring for k in adjacency.get(j, ()) if k in inside} - group
            group |= ring
            if sum(len(pts.of(j)) for j in group) >= options.min_plane_points:
                break
        fit(i, group)
    return out
