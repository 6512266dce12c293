"""The ground texture in tiles on disk: a city's ground does not fit in memory.

At 0.5 m a texel, the ground's heights, texture and labels take some 200 MB a square
kilometre. The ground cut (section 5.4) is a task per tile, which leaves its tile on the
run's shelf; the ring cuts (section 5.3) paint the tiles through a small cache, in the
buildings' order, so that a ring read what the rings before it painted, as on one whole
texture; the textured ground is then made a tile at a time.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from workbench.engine import TaskStore
from workbench.raster import Grid

HEIGHTS, CUT, PAINTED = "ground_z", "ground_cut", "ground_painted"  # the shelf's stages


@dataclass(frozen=True)
class GroundTiles:
    """The ground grid cut into square tiles, each tile's arrays on ``shelf``.

    Attributes
    ----------
    grid : Grid
        The whole ground grid.
    size : int
        Texels per side of a tile (the last of a row or column smaller).
    shelf : TaskStore
        Where the tiles' arrays are, stage by stage (:data:`HEIGHTS`: (h, w) float metres,
        :data:`CUT` and :data:`PAINTED`: (h, w, 3) uint8), keyed by the tile's index.
    """

    grid: Grid
    size: int
    shelf: TaskStore

    @property
    def tiles(self) -> list[tuple[slice, slice]]:
        """Rows and columns of every tile, row by row."""
        return self.grid.tiles(self.size)

    def overlapping(self, rows: slice, cols: slice):
        """Yields (tile index, the window's part in the tile's cells, that part in the
        window's cells) for every tile the window ``rows`` x ``cols`` overlaps."""
        per_row = -(-self.grid.width // self.size)
        s = self.size
        for tr in range(rows.start // s, (rows.stop - 1) // s + 1):
            for tc in range(cols.start // s, (cols.stop - 1) // s + 1):
                r0, r1 = max(rows.start, tr * s), min(rows.stop, (tr + 1) * s)
                c0, c1 = max(cols.start, tc * s), min(cols.stop, (tc + 1) * s)
                in_tile = slice(r0 - tr * s, r1 - tr * s), slice(c0 - tc * s, c1 - tc * s)
                in_window = (slice(r0 - rows.start, r1 - rows.start),
                             slice(c0 - cols.start, c1 - cols.start))  # fmt: skip
                yield tr * per_row + tc, in_tile, in_window

    def read(self, stage: str, rows: slice, cols: slice) -> np.ndarray:
        """The window ``rows`` x ``cols`` of ``stage``'s arrays on the shelf."""
        return self.assemble(rows, cols, lambda k: self.shelf.load(stage, str(k)))

    def assemble(self, rows: slice, cols: slice, load) -> np.ndarray:
        """The window ``rows`` x ``cols`` put together from its tiles' arrays, ``load(k)``
        giving tile ``k``'s."""
        out = None
        for k, in_tile, in_window in self.overlapping(rows, cols):
            tile = load(k)
            if out is None:
                shape = (rows.stop - rows.start, cols.stop - cols.start, *tile.shape[2:])
                out = np.empty(shape, tile.dtype)
            out[in_window] = tile[in_tile]
        return out


class PaintedGround:
    """The ground texture's tiles as the ring cuts paint them: the last ``cached`` tiles
    used are held, the others wait on the shelf (:data:`PAINTED` once painted, else the
    ground cut's :data:`CUT`). Start on a clean stage: a run resumed repaints every ring."""

    def __init__(self, tiles: GroundTiles, cached: int = 16):
        self.tiles, self.cached = tiles, cached
        self._held: OrderedDict[int, np.ndarray] = OrderedDict()
        self._changed: set[int] = set()
        tiles.shelf.clear(PAINTED)

    def _tile(self, k: int) -> np.ndarray:
        if k in self._held:
            self._held.move_to_end(k)
            return self._held[k]
        shelf = self.tiles.shelf
        stage = PAINTED if shelf.has(PAINTED, str(k)) else CUT
        self._held[k] = shelf.load(stage, str(k))
        while len(self._held) > self.cached:
            old, image = self._held.popitem(last=False)
            if old in self._changed:
                shelf.save(PAINTED, str(old), image)
                self._changed.discard(old)
        return self._held[k]

    def read(self, rows: slice, cols: slice) -> np.ndarray:
        """(h, w, 3) uint8, a copy of the texture in ``rows`` x ``cols``."""
        return self.tiles.assemble(rows, cols, self._tile)

    def paint(self, rows: slice, cols: slice, image: np.ndarray) -> None:
        """Put ``image`` (h, w, 3) into the texture at ``rows`` x ``cols``."""
        for k, in_tile, in_window in self.tiles.overlapping(rows, cols):
            self._tile(k)[in_tile] = image[in_window]
            self._changed.add(k)
