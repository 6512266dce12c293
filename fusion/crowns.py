"""The top surface of tree crowns, which the median of a cell's heights misses.

A crown overhangs the ground at its rim: oblique views see the ground beneath it, and
those points are the cell's trusted ones, while the crown's own points there are steep
(the crown curves down to its rim) or beside the depth edge of its silhouette, so the
weighted median reads the ground. Two corrections, not in the paper:

- :func:`crown_sightings`: where the views' forest sees a tree in enough of a cell's
  observations, their height is the crown's (needs only the per-view classes);
- :func:`crown_tops`: in and beside the fused tree cells, an upper quantile of the
  trusted heights instead of their median (needs the fused classes).

Beside a building neither holds: the higher observations there are the wall's and the
roof edge's, so once the classes are known, the cells beside a building keep their median
(:func:`sightings_clear_of_buildings`, and :func:`crown_tops` itself).
"""

from __future__ import annotations

import cv2
import numpy as np

from workbench.robust import group_weighted_quantile

CROWN_QUANTILE = 0.7  # of a crown cell's weighted heights (crown_tops)
CROWN_REACH_M = 0.5  # cells this close to a tree cell are crown cells ...
CROWN_CLEAR_M = 0.75  # ... unless this close to a building cell
SIGHTING_PROBABILITY = 0.67  # a view's tree probability that makes its point a sighting
SIGHTINGS = 5  # a cell's crown height needs this many sightings ...
SIGHTING_SHARE = 0.3  # ... making up this share of its observations
BENEATH_TOP_M = 2.0  # a point this far below its cell's top surface saw under it


def crown_sightings(
    cells: np.ndarray,
    z: np.ndarray,
    weight: np.ndarray,
    tree_probability: np.ndarray,
    median: np.ndarray,
    *,
    min_probability: float = SIGHTING_PROBABILITY,
    min_sightings: int = SIGHTINGS,
    min_share: float = SIGHTING_SHARE,
    beneath_m: float = BENEATH_TOP_M,
) -> np.ndarray:
    """(n_cells,) float32 height of the crown the views see over each cell whose median
    reads the ground beneath it, NaN elsewhere.

    A sighting is an observation whose own view gives it a tree probability above
    ``min_probability``: at a crown's rim the views that see the crown still classify
    its pixels as tree, though their points are not trusted for the median. Where a
    cell has at least ``min_sightings`` sightings, making up at least ``min_share`` of
    its observations, the crown's height is their weighted median; where the cell's
    median lies more than ``beneath_m`` below it, the median saw under the crown. On
    ``small`` seeds 0, 1 and 2, raising those cells to the crown took the DSM RMSE off
    the height jumps from 0.53, 0.52 and 0.53 m to 0.46, 0.44 and 0.44 m.

    Parameters
    ----------
    cells : (N,) int64 cell index of each visible observation
    z : (N,) float heights, metres
    weight : (N,) float weights of the heights (:func:`~fusion.observations.height_weights`)
    tree_probability : (N,) float in [0, 1], from the observation's own view
    median : (n_cells,) float the cells' (weighted median) heights, metres, NaN unknown
    """
    n_cells = len(median)
    sighted = tree_probability > min_probability
    n_seen = np.bincount(cells, minlength=n_cells)
    n_sighted = np.bincount(cells[sighted], minlength=n_cells)
    height = group_weighted_quantile(cells[sighted], z[sighted], weight[sighted], n_cells, 0.5)
    enough = (n_sighted >= min_sightings) & (n_sighted >= min_share * n_seen)
    with np.errstate(invalid="ignore"):
        beneath = median < height - beneath_m
    return np.where(enough & beneath, height, np.nan).astype(np.float32)


def near_class(classes: np.ndarray, code: int, metres: float, gsd: float) -> np.ndarray:
    """(H, W) bool: cells within ``metres`` (a square of whole cells, at least one) of a
    cell of class ``code``."""
    r = max(1, int(round(metres / gsd)))
    mask = (classes == code).astype(np.uint8)
    return cv2.dilate(mask, np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0


def sightings_clear_of_buildings(
    dsm: np.ndarray,
    median: np.ndarray,
    sighted: np.ndarray,
    classes: np.ndarray,
    gsd: float,
    clear_m: float = CROWN_CLEAR_M,
) -> tuple[np.ndarray, np.ndarray]:
    """The DSM with the crown sightings (:func:`crown_sightings`) undone beside buildings.

    The views' forest calls tree some of the points on a wall and on the ramps that dense
    matching draws from a roof's edge down to the ground, and in the ground cells at the
    wall's foot those sightings, metres above the ground, raised the cell to a height
    between the ground and the eaves. Known only once the classes are, the cells within
    ``clear_m`` of a building cell take back their median, as :func:`crown_tops` leaves
    them. On ``small`` seeds 0, 1 and 2 it took the DSM RMSE off the height jumps from
    0.481, 0.432 and 0.451 m to 0.460, 0.436 and 0.430 m, the classes unchanged.

    Parameters
    ----------
    dsm : (H, W) float
        Heights with the sightings' heights, metres (NaN unknown).
    median : (H, W) float
        The same cells' weighted medians, before the sightings, metres.
    sighted : (H, W) bool
        Cells whose height the sightings gave.
    classes : (H, W) int
        Class codes (4 building).
    gsd : float
        Cell size, metres.

    Returns
    -------
    dsm : (H, W) float32
    cleared : (H, W) bool, the sighted cells given back their median
    """
    cleared = sighted & near_class(classes, 4, clear_m, gsd)
    return np.where(cleared, median, dsm).astype(np.float32), cleared


def crown_tops(
    dsm: np.ndarray,
    upper: np.ndarray,
    classes: np.ndarray,
    gsd: float,
    reach_m: float = CROWN_REACH_M,
    clear_m: float = CROWN_CLEAR_M,
) -> tuple[np.ndarray, np.ndarray]:
    """The DSM with the cells in and beside tree crowns raised to an upper quantile of
    their heights.

    A DSM is the top surface, but under a crown's edge the oblique views see the ground
    beneath it: the weighted median of such a cell mixes crown and ground and reads
    metres low, and the fused class there is often grass or ground too, which is why the
    cells within ``reach_m`` of a tree cell count. Beside a wall it is the other way
    round, the higher observations being the ones to distrust (facade and roof-edge
    points spilling into the ground cell), so cells within ``clear_m`` of a building
    keep their median. On ``small`` (seeds 0, 1, 2) the 0.7 quantile took the DSM RMSE
    off the height jumps from 0.61, 0.64 and 0.68 m to 0.54, 0.53 and 0.53 m.

    Parameters
    ----------
    dsm : (H, W) float
        Weighted medians, metres (NaN unknown).
    upper : (H, W) float
        The same observations' ``CROWN_QUANTILE`` weighted quantiles, metres.
    classes : (H, W) int
        Class codes (3 tree, 4 building).
    gsd : float
        Cell size, metres.

    Returns
    -------
    dsm : (H, W) float32
    raised : (H, W) bool, the cells that took the upper quantile
    """
    raised = near_class(classes, 3, reach_m, gsd) & ~near_class(classes, 4, clear_m, gsd)
    raised &= np.isfinite(upper) & np.isfinite(dsm) & (upper > dsm)
    return np.where(raised, upper, dsm).astype(np.float32), raised
