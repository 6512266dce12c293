"""A grid cut into blocks, each worked on with a margin around it, for work whose memory
must follow the block and not the area (the fusion's and the modeling paths' ``--block``).

A block owns its ``inner`` cells; it is worked on over its ``outer`` cells, the inner
ones and a margin, so that whatever straddles the inner edge (a building, an opening of
the ground filter) is whole in the block that keeps it. The margin is therefore about
the largest building's width.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .options import LARGEST_BUILDING_M
from .raster import Grid

AUTO_BLOCK_CELLS = 4096  # a grid of at most this many cells a side is worked at once


@dataclass(frozen=True)
class Block:
    """A block of the grid: the cells it owns (``inner``) and the cells it is worked over
    (``outer``: ``inner`` and the margin, clipped to the grid), as (rows, cols) slices of
    the whole grid."""

    index: int
    inner: tuple[slice, slice]
    outer: tuple[slice, slice]

    @property
    def origin(self) -> tuple[int, int]:
        """(row, col) of the first outer cell in the whole grid."""
        return self.outer[0].start, self.outer[1].start

    @property
    def inside(self) -> tuple[slice, slice]:
        """``inner`` as slices of the outer block's arrays."""
        return tuple(
            slice(i.start - o.start, i.stop - o.start)
            for i, o in zip(self.inner, self.outer, strict=True)
        )

    def cut_edges(self, shape: tuple[int, int]) -> tuple[bool, bool, bool, bool]:
        """Whether the outer cells stop short of the grid's (``shape``) north, south, west
        and east edges: the sides where the block cuts what lies across them."""
        rows, cols = self.outer
        return rows.start > 0, rows.stop < shape[0], cols.start > 0, cols.stop < shape[1]


def whole_grid_block(grid: Grid) -> Block:
    """The one block of a grid worked at once."""
    whole = (slice(0, grid.height), slice(0, grid.width))
    return Block(0, whole, whole)


def block_layout(grid: Grid, block_m: float, margin_m: float = LARGEST_BUILDING_M) -> list[Block]:
    """The blocks of at most ``block_m`` metres a side that cut ``grid`` most evenly, each
    with ``margin_m`` metres of margin, row by row from the north-west.

    Parameters
    ----------
    grid : Grid
    block_m, margin_m : float
        A block's side and its margin, metres.
    """
    size = max(1, int(block_m / grid.gsd))
    margin = int(np.ceil(margin_m / grid.gsd))
    cuts = []
    for n in (grid.height, grid.width):
        k = -(-n // size)  # blocks along the axis
        cuts.append(np.linspace(0, n, k + 1).round().astype(int))
    blocks = []
    for r0, r1 in zip(cuts[0][:-1], cuts[0][1:], strict=True):
        for c0, c1 in zip(cuts[1][:-1], cuts[1][1:], strict=True):
            inner = (slice(int(r0), int(r1)), slice(int(c0), int(c1)))
            outer = tuple(
                slice(max(0, a - margin), min(n, b + margin))
                for a, b, n in ((int(r0), int(r1), grid.height), (int(c0), int(c1), grid.width))
            )
            blocks.append(Block(len(blocks), inner, outer))
    return blocks


def auto_block_size(grid: Grid, margin_m: float = LARGEST_BUILDING_M) -> float | None:
    """The side of the blocks chosen by default, metres: none (the whole grid at once) up
    to :data:`AUTO_BLOCK_CELLS` cells a side, else blocks of that many cells with their
    margins."""
    if max(grid.shape) <= AUTO_BLOCK_CELLS:
        return None
    return (AUTO_BLOCK_CELLS - 2 * np.ceil(margin_m / grid.gsd)) * grid.gsd
