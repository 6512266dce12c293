"""Connected regions of a raster mask as polygons, a strip of rows at a time.

GDAL's polygoniser (``rasterio.features.shapes``) takes the whole array: a city's
building class at 0.5 m is 400 M cells a 100 km². Here the mask is read and polygonised
a strip of rows at a time; a region that crosses a strip's edge comes out in pieces,
which are put together (their union) once every strip is read, by the cells they share
across the edges (a union-find over the strips' labels).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import rasterio.features
import shapely
from scipy import ndimage
from shapely.geometry import Polygon, shape

from .raster import Grid

STRIP_CELLS = 2**22  # cells of a strip of rows: 4 M, some 30 MB with its labels


def mask_regions(
    read: Callable[[slice], np.ndarray], grid: Grid, strip_cells: int | None = None
) -> list[Polygon]:
    """The 4-connected regions of a mask, as polygons in world metres.

    Parameters
    ----------
    read : callable
        ``read(rows)`` gives the mask's (h, W) bool rows ``rows`` (a slice).
    grid : Grid
        The mask's grid.
    strip_cells : int, optional
        Cells read at once (default :data:`STRIP_CELLS`): strips of ``strip_cells // W``
        rows (at least one).

    Returns
    -------
    list of Polygon
        One per region, with its holes, in the order the polygoniser gives a whole
        mask's when it is one strip; a region in pieces where its first piece came.
    """
    step = max(1, (strip_cells or STRIP_CELLS) // max(grid.width, 1))
    pieces: dict[int, list] = {}  # a region's pieces, by the label of its first piece
    parent: dict[int, int] = {}
    above = None  # the last row's labels of the strip above
    offset = 0
    for r0 in range(0, grid.height, step):
        rows = slice(r0, min(r0 + step, grid.height))
        mask = np.asarray(read(rows), bool)
        labels, n = ndimage.label(mask)  # 4-connected, as the polygoniser's connectivity
        labels = np.where(mask, labels + offset, 0).astype(np.int32)
        # in the strip's cells, then in world metres from the whole grid's corner: the
        # strips' common edges get the same coordinates, to the last bit
        for geom, value in rasterio.features.shapes(labels, mask=mask, connectivity=4):
            piece = shapely.transform(shape(geom), lambda cr, r0=r0: _world(cr, r0, grid))
            pieces.setdefault(int(value), []).append(piece)
            parent.setdefault(int(value), int(value))
        if above is not None:
            meet = (above > 0) & (labels[0] > 0)
            for a, b in set(zip(above[meet].tolist(), labels[0][meet].tolist(), strict=True)):
                _join(parent, a, b)
        above = labels[-1]
        offset += n
    regions: dict[int, list] = {}
    for label, polys in pieces.items():  # in the order the pieces came
        regions.setdefault(_root(parent, label), []).extend(polys)
    return [p[0] if len(p) == 1 else shapely.union_all(p) for p in regions.values()]


def _world(cr: np.ndarray, r0: int, grid: Grid) -> np.ndarray:
    """(N, 2) world x, y of cell corners (N, 2) (column, row in a strip from row ``r0``),
    as GDAL applies a north-up geotransform."""
    return np.column_stack(
        [grid.xmin + cr[:, 0] * grid.gsd, grid.ymax + (cr[:, 1] + r0) * -grid.gsd]
    )


def _root(parent: dict, a: int) -> int:
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


def _join(parent: dict, a: int, b: int) -> None:
    ra, rb = _root(parent, a), _root(parent, b)
    if ra != rb:
        parent[max(ra, rb)] = min(ra, rb)  # the earlier piece's label stands for both
