"""A mask's regions polygonised a strip of rows at a time (workbench/regions.py)."""

import numpy as np
import pytest
import rasterio.features
from shapely.geometry import shape

from workbench.raster import Grid
from workbench.regions import mask_regions

# a U whose arms meet only in the last row, a ring around a courtyard, two cells that
# touch at a corner only (two regions: 4-connected), a lone cell
HAND = """
#.#..###.
#.#..#.#.
#.#..###.
#.#......
###.#....
.....#..#
"""


def _mask(text: str) -> np.ndarray:
    return np.array([[ch == "#" for ch in line] for line in text.strip().splitlines()])


def _whole(mask: np.ndarray, grid: Grid) -> list:
    return [shape(g) for g, _ in rasterio.features.shapes(
        mask.astype(np.uint8), mask=mask, transform=grid.transform, connectivity=4)]  # fmt: skip


def _same_regions(mine: list, theirs: list) -> bool:
    left = list(theirs)
    for p in mine:
        match = [i for i, q in enumerate(left) if p.equals(q)]
        if len(match) != 1:
            return False
        left.pop(match[0])
    return not left


def test_regions_in_strips_of_every_height_are_the_whole_masks():
    mask = _mask(HAND)
    grid = Grid(500.0, 900.0, 0.5, mask.shape[1], mask.shape[0])
    whole = _whole(mask, grid)
    assert len(whole) == 5
    one = mask_regions(lambda rows: mask[rows], grid, strip_cells=10**9)
    assert [p.wkt for p in one] == [p.wkt for p in whole]  # one strip: the polygoniser's
    for h in range(1, mask.shape[0]):
        mine = mask_regions(lambda rows: mask[rows], grid, strip_cells=h * grid.width)
        assert _same_regions(mine, whole), h
    u = max(one, key=lambda p: p.area)
    assert u.area == pytest.approx(11 * 0.25) and len(u.interiors) == 0
    ring = [p for p in one if len(p.interiors) == 1]
    assert len(ring) == 1 and ring[0].area == pytest.approx(8 * 0.25)


def test_random_masks_in_strips_are_the_whole_masks():
    """At UTM coordinates with a 0.3 m cell, where a strip's own geotransform would put
    the strips' common edges a few ulps apart (and no region in pieces would equal the
    whole mask's)."""
    rng = np.random.default_rng(3)
    for _ in range(5):
        mask = rng.random((40, 30)) < 0.55
        grid = Grid(499_873.3, 5_401_211.7, 0.3, 30, 40)
        whole = _whole(mask, grid)
        for h in (1, 3, 7):
            mine = mask_regions(lambda rows, m=mask: m[rows], grid, strip_cells=h * 30)
            assert _same_regions(mine, whole)
