"""Free space over the cells the views saw: no surface stands where a view sees past.

A view whose pixel sees a surface beyond a point has looked through the point: the
point is empty (the free space a depth map carves, as volumetric fusions use it; over
the cells no view saw, :mod:`fusion.hidden_ceiling` keeps the same bound). A 2.5D DSM
is solid from its height down to the ground, so a cell whose fused height stands above
a point of its column some view sees past is contradicted by that view.

Two kinds of cells are, on the synthetic city:

* beside a tall wall, in an alley few views see the bottom of, the points of the wall
  that a view sees nearly edge-on: its strip is a few pixels wide, their normals
  smoothed with the roof's look level, and the cell reads a height between the ground
  and the eaves. Their height is fused again from the observations below the free
  space (:func:`fusion.scene_fusion.under_free_space`);
* a crown the forest calls building: rays pass beneath a canopy, never through a
  building. An object (connected cells above the ground, not classed tree) most of
  whose cells the views see through is a crown (:func:`porous_objects`).

A crown classed tree keeps its height: free space beneath its canopy is what a crown
has. A point is seen past only where every pixel around its projection (3 x 3) lies
beyond it, since a cell's centre projects to within a pixel of its true place.
Figures: ``docs/fusion.md``, step 13.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage as ndi

from workbench.engine import Engine
from workbench.raster import GRASS, GROUND, TREE, Grid

from .hidden_ceiling import (
    HiddenColumns,
    ceiling_raster,
    column_ceilings,
    columns_in_view,
    hidden_columns_of,
    trusted_depth,
)

# a point is seen past when every pixel of this neighbourhood of its projection is
NEIGHBOURHOOD_PX = 3
# an object is a crown when the views see through at least this share of its cells: a
# majority (on ``small`` seeds 0-2 and dev seeds 6, 7, 10 the building objects' shares
# are 0.00, the crowns classed building 0.53-0.84)
POROUS_SHARE = 0.5


def nearest_around(depth: np.ndarray, size: int = NEIGHBOURHOOD_PX) -> np.ndarray:
    """(H, W) float32: the nearest depth of each pixel's ``size`` x ``size``
    neighbourhood, 0 where one of them is unknown (NaN), as nothing is known to lie
    beyond it."""
    d = np.nan_to_num(np.asarray(depth, np.float32), nan=0.0)
    return cv2.erode(d, np.ones((size, size), np.uint8), borderType=cv2.BORDER_CONSTANT,
                     borderValue=0.0)  # fmt: skip


def elevated_columns(dsm: np.ndarray, ground: np.ndarray, grid: Grid,
                     tolerance: float) -> tuple[np.ndarray, np.ndarray, HiddenColumns]:  # fmt: skip
    """The seen cells standing more than ``tolerance`` above ``ground`` (rows and
    columns, (n,) int) and their columns, tested from the ground up to ``tolerance``
    below the DSM (:class:`~fusion.hidden_ceiling.HiddenColumns` with ``limit``), in
    order of that limit so that each chunk of them tests about the same heights.

    dsm : (H, W) float, metres, NaN unknown; ground : (H, W) float, metres, everywhere.
    """
    with np.errstate(invalid="ignore"):
        elevated = np.isfinite(dsm) & (dsm - ground > tolerance)
    r, c = np.nonzero(elevated)
    limit = dsm[r, c].astype(np.float64) - tolerance
    order = np.argsort(limit, kind="stable")
    r, c, limit = r[order], c[order], limit[order]
    x, y = grid.cell_center(r, c)
    top = float(limit.max(initial=0.0))
    return r, c, HiddenColumns(x, y, ground[r, c].astype(np.float64), top, grid.gsd,
                               limit=limit)  # fmt: skip


def view_ceilings_and_free_space(i: int, views: list, hidden: HiddenColumns,
                                 elevated: HiddenColumns, tolerance: float) -> tuple:  # fmt: skip
    """Task: view ``i``'s lowest heights seen past over the ``hidden`` columns (its
    trusted depth, :func:`~fusion.hidden_ceiling.column_ceilings`) and over the
    ``elevated`` ones (with every pixel around each projection, :func:`nearest_around`),
    each (n,) float32, +inf none: the depth map read and screened once for both, and
    not at all by a view that sees none of the columns (a block of a city that the view
    does not look at: the results are those of the test, all +inf)."""
    v = views[i]
    seen_hidden = columns_in_view(v.camera, hidden)
    seen_elevated = columns_in_view(v.camera, elevated)
    if not (seen_hidden.any() or seen_elevated.any()):
        return (np.full(len(hidden.x), np.inf, np.float32),
                np.full(len(elevated.x), np.inf, np.float32))  # fmt: skip
    depth = trusted_depth(v.read_depth())
    free = nearest_around(depth) if len(elevated.x) else depth  # none: nothing to read
    return (column_ceilings(v.camera, depth, hidden, tolerance, seen_hidden),
            column_ceilings(v.camera, free, elevated, tolerance, seen_elevated))  # fmt: skip


@dataclass
class FreeSpace:
    """:func:`ceilings_and_free_space`'s rasters: (H, W) float32 ``ceiling`` over the
    cells no view saw (:func:`~fusion.hidden_ceiling.hidden_ceilings`'), NaN elsewhere;
    over each seen cell standing more than the tolerance above the ground, the lowest
    height at which a view sees past its column up to the tolerance below its DSM
    (``lowest``, NaN where none does and elsewhere) and how many views do (``views``,
    (H, W) int32)."""

    ceiling: np.ndarray
    lowest: np.ndarray
    views: np.ndarray


def ceilings_and_free_space(engine: Engine, shared_views, n_views: int, grid: Grid,
                            dsm: np.ndarray, ground: np.ndarray, tolerance: float,
                            free_space: bool = True) -> FreeSpace:  # fmt: skip
    """The ceiling over the cells no view saw and the free space over the elevated seen
    cells, a view's task each (:func:`view_ceilings_and_free_space`). The parameters
    are :func:`~fusion.hidden_ceiling.hidden_ceilings`'; ``tolerance`` (metres) is also
    how far below the DSM a ray must pass. ``free_space`` False: the ceiling alone (no
    column of a seen cell is tested; ``lowest`` all NaN, ``views`` 0).
    """
    hidden, hidden_cols = hidden_columns_of(dsm, ground, grid)
    rows, cols, columns = elevated_columns(dsm if free_space else np.full_like(dsm, np.nan),
                                           ground, grid, tolerance)  # fmt: skip
    ceiling = np.full(len(hidden_cols.x), np.float32(hidden_cols.top), np.float32)
    lowest = np.full(len(columns.x), np.inf, np.float32)
    past = np.zeros(len(columns.x), np.int32)
    if len(hidden_cols.x) or len(columns.x):
        shared = engine.share((hidden_cols, columns))  # a city's are megabytes: sent once
        for above_hidden, seen in engine.map(_view_task, range(n_views), shared_views, shared,
                                             tolerance, stage="ceiling"):  # fmt: skip
            np.minimum(ceiling, above_hidden, out=ceiling)
            np.minimum(lowest, seen, out=lowest)
            past += np.isfinite(seen)
    free = np.full(grid.shape, np.nan, np.float32)
    views = np.zeros(grid.shape, np.int32)
    free[rows, cols] = np.where(np.isfinite(lowest), lowest, np.nan)
    views[rows, cols] = past
    return FreeSpace(ceiling_raster(hidden, ceiling), free, views)


def _view_task(i: int, views: list, columns: tuple, tolerance: float) -> tuple:
    return view_ceilings_and_free_space(i, views, *columns, tolerance)


def seen_through(free: np.ndarray, prob_sum: np.ndarray,
                 elevated: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The cells whose height the free space contradicts, and the crowns.

    Of the ``elevated`` cells not classed tree, those a view sees past below their
    height (``free`` known) are seen through. An object of them most of whose cells are
    seen through is a crown (:func:`porous_objects`). The others' heights are
    contradicted, unless the views give tree at least a chance's share of their votes
    (a crown's canopy merged into a building's object).

    Parameters
    ----------
    free : (H, W) float
        :class:`FreeSpace`'s ``lowest`` heights seen past, metres, NaN none.
    prob_sum : (K, H, W) float
        Accumulated class probabilities (ground, grass, tree, building), 0 or NaN
        unseen.
    elevated : (H, W) bool
        The seen cells standing above the ground that may be tested.

    Returns
    -------
    contradicted, porous : (H, W) bool
    """
    p = np.nan_to_num(np.asarray(prob_sum, np.float64))
    total = p.sum(axis=0)
    tree = p.argmax(axis=0) == TREE - 1
    solid = elevated & (total > 0) & ~tree
    through = solid & np.isfinite(free)
    porous = porous_objects(through, solid)
    with np.errstate(invalid="ignore", divide="ignore"):
        tree_share = p[TREE - 1] / total
    return through & ~porous & (tree_share < 1 / len(p)), porous


def relabel_porous(prob_sum: np.ndarray, porous: np.ndarray) -> None:
    """In ``prob_sum`` ((K, H, W), in place), tree and the most probable class trade
    places at the ``porous`` cells ((H, W) bool): tree becomes the most probable and
    every confidence is kept."""
    r, c = np.nonzero(porous)
    _trade_places(prob_sum, r, c, np.full(len(r), TREE - 1))


def relabel_grounded(prob_sum: np.ndarray, grounded: np.ndarray) -> None:
    """In ``prob_sum`` ((K, H, W), in place), at the ``grounded`` cells ((H, W) bool:
    those the free space put on the ground), the more probable of ground and grass
    trades places with the most probable class. Their votes are the points the free
    space contradicts, a wall's (building) or a canopy's (tree), which the elevation
    prior's damping cannot overturn where nothing else voted; a cell on the ground is
    neither."""
    r, c = np.nonzero(grounded)
    flat = np.nan_to_num(prob_sum[GROUND - 1 : GRASS, r, c], nan=-1.0).argmax(axis=0)
    _trade_places(prob_sum, r, c, flat + GROUND - 1)


def _trade_places(prob_sum: np.ndarray, r: np.ndarray, c: np.ndarray, to: np.ndarray) -> None:
    """At cells (``r``, ``c``), class index ``to`` (per cell) and the most probable class
    trade their votes in ``prob_sum`` (in place)."""
    p = prob_sum[:, r, c]
    best = np.nan_to_num(p, nan=-1.0).argmax(axis=0)
    cols = np.arange(len(r))
    p[to, cols], p[best, cols] = p[best, cols], p[to, cols].copy()
    prob_sum[:, r, c] = p


def porous_objects(seen_through: np.ndarray, solid_candidates: np.ndarray,
                   share: float = POROUS_SHARE) -> np.ndarray:  # fmt: skip
    """(H, W) bool: the objects (8-connected groups of ``solid_candidates``, cells above
    the ground not classed tree) of which at least ``share`` of the cells are
    ``seen_through``: crowns, as nothing is seen through a building."""
    labels, n = ndi.label(solid_candidates, np.ones((3, 3), bool))
    if not n:
        return np.zeros(seen_through.shape, bool)
    size = np.bincount(labels.ravel(), minlength=n + 1)
    through = np.bincount(labels.ravel(), (seen_through & solid_candidates).ravel(),
                          minlength=n + 1)  # fmt: skip
    porous = through >= share * np.maximum(size, 1)
    porous[0] = False
    return porous[labels]
