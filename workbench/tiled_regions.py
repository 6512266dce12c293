"""Connected regions of a mask over a grid's tiles, the mask never whole in memory.

A fusion run's buildings, to the evaluation, are the 8-connected regions of its building
class of at least a given area. On a city's grid the mask and its labels are gigabytes;
here each tile is labelled on its own (OpenCV), the labels that touch across the tiles'
edges are joined (a graph's connected components, SciPy), and what is kept is one number
per tile label: its region's id, 0 for a region too small. A tile labelled again later
(OpenCV labels the same mask the same way) is then its regions' ids.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

Tile = tuple[slice, slice]


def tile_labels(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(h, w) int32 8-connected labels of ``mask`` (0 off it, 1..n) and (n,) their sizes."""
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    return labels, stats[1:, cv2.CC_STAT_AREA].astype(np.int64)


class TiledRegions:
    """The 8-connected regions of at least ``min_cells`` cells of a mask, read a tile at
    a time.

    Parameters
    ----------
    tiles : list of (rows, cols) slices
        Tiles covering the grid without overlap, in rows of tiles (``Grid.tiles``).
    mask_of : callable (rows, cols) -> (h, w) bool
        The mask on a tile.
    min_cells : float
        Smallest region kept.

    Notes
    -----
    Memory: the labels along the tiles' edges and one id per tile label, so a few bytes
    per tile row of cells, not per cell.
    """

    def __init__(self, tiles: list[Tile], mask_of: Callable[[slice, slice], np.ndarray],
                 min_cells: float):  # fmt: skip
        self.mask_of = mask_of
        self.offset: dict[tuple[int, int], int] = {}
        sizes, edges = [np.zeros(1, np.int64)], {}
        n = 0
        for rows, cols in tiles:
            labels, size = tile_labels(mask_of(rows, cols))
            g = np.where(labels > 0, labels.astype(np.int64) + n, 0)
            self.offset[rows.start, cols.start] = n
            edges[rows.start, cols.start] = (rows, cols, g[0], g[-1], g[:, 0], g[:, -1])
            sizes.append(size)
            n += len(size)
        pairs = _edge_pairs(list(edges.values()))
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n + 1, n + 1))
        _, region = connected_components(graph, directed=False)
        size = np.bincount(region, weights=np.concatenate(sizes))
        kept = size[region] >= min_cells
        kept[0] = False  # node 0 is the background
        ids = np.zeros(len(size), np.int64)
        ids[np.unique(region[kept])] = np.arange(1, len(np.unique(region[kept])) + 1)
        self.ids = ids[region]
        self.count = int(ids.max()) if len(ids) else 0

    def __call__(self, rows: slice, cols: slice, mask: np.ndarray | None = None) -> np.ndarray:
        """(h, w) int64 region ids on a tile of the list (0: off the mask or too small);
        ``mask`` is the tile's mask when the caller has read it."""
        mask = self.mask_of(rows, cols) if mask is None else mask
        labels, _ = tile_labels(mask)
        g = np.where(labels > 0, labels.astype(np.int64) + self.offset[rows.start, cols.start], 0)
        return self.ids[g]


def _edge_pairs(edges: list) -> np.ndarray:
    """(P, 2) pairs of labels that touch (8-connected) across the tiles' edges, from each
    tile's (rows, cols, top, bottom, left, right) edge labels."""
    pairs = [np.zeros((0, 2), np.int64)]
    # across a row of tiles' lower edge: the full rows above and below, so that the
    # diagonals through the tiles' corners count too
    starts = sorted({rows.start for rows, *_ in edges})
    for r in starts[1:]:
        above = np.concatenate([e[3] for e in sorted(edges, key=lambda e: e[1].start)
                                if e[0].stop == r])  # fmt: skip
        below = np.concatenate([e[2] for e in sorted(edges, key=lambda e: e[1].start)
                                if e[0].start == r])  # fmt: skip
        pairs.append(_touching(above, below))
    by_corner = {(e[0].start, e[1].start): e for e in edges}
    for rows, cols, *_, right in edges:  # across a tile's right edge, within its rows
        nb = by_corner.get((rows.start, cols.stop))
        if nb is not None:
            pairs.append(_touching(right, nb[4]))
    return np.concatenate(pairs)


def _touching(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P, 2) pairs of labels of two adjacent lines of cells ``a`` and ``b`` (same
    length) that are 8-neighbours, both > 0."""
    out = []
    for d in (-1, 0, 1):
        x = a[max(0, -d) : len(a) - max(0, d)]
        y = b[max(0, d) : len(b) - max(0, -d)]
        both = (x > 0) & (y > 0)
        out.append(np.column_stack([x[both], y[both]]))
    return np.unique(np.concatenate(out), axis=0)
