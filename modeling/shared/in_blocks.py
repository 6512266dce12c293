"""A modeling path over a grid too large to hold: the grid cut into blocks
(:mod:`workbench.grid_blocks`), each segmented over its outer cells, and each segment
modelled by exactly one block.

A block's margin is about the largest building's width, so a building the block's inner
edge cuts is whole over its outer cells, in this block and in its neighbour. Each block
segments its own outer cells, and two blocks may draw the same building a cell apart.
:class:`SegmentClaims` therefore decides, block after block, which segments a block
models: one whose centre lies in its inner cells, or in the inner cells of a block
before it that did not model it, unless a block before it already modelled most of its
cells. No building is then modelled twice or lost between two blocks. A segment cut by
the outer edge is left to the block whose inner cells hold its centre, which models the
part it holds when the segment is wider than the margin (counted, and warned of).

:class:`BlockRasters` puts the blocks' inner cells of the rasters a run writes together;
:class:`BlockPlan` keeps the blocks' buildings on disk as they come.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from modeling.shared.raster_ground import GROUND_CELL_M, ground_surface
from workbench.engine import Engine
from workbench.fusion_run import fusion_header
from workbench.grid_blocks import Block, auto_block_size, block_layout, whole_grid_block
from workbench.meshes import concatenate_meshes
from workbench.model_run import Building, BuildingsOnDisk, Surface, SurfacePieces
from workbench.progress import progress
from workbench.raster import Grid, RasterWindows, WindowedRaster, decimated_cells, read_decimated

log = logging.getLogger(__name__)


def model_blocks(grid: Grid, block_m: float | None, margin_m: float) -> tuple[list[Block], float]:
    """The blocks a path models ``grid`` in: of ``block_m`` metres a side with
    ``margin_m`` of margin; by default (None) the whole grid at once up to
    :data:`~workbench.grid_blocks.AUTO_BLOCK_CELLS` cells a side. Returns them and their
    side (None for the whole grid)."""
    block_m = block_m if block_m is not None else auto_block_size(grid, margin_m)
    if block_m is None:
        return [whole_grid_block(grid)], None
    blocks = block_layout(grid, block_m, margin_m)
    log.info("%d blocks of %g m with %g m of margin", len(blocks), block_m, margin_m)
    return blocks, block_m


@dataclass
class BlockPlan:
    """A path's run over a fusion's grid in blocks: the grid, its blocks (``side_m``:
    their side, None for the whole grid), which block models which segment, the rasters
    the run writes and the buildings modelled so far (on disk with several blocks and a
    task store, so that the run never holds them all)."""

    grid: Grid
    blocks: list[Block]
    side_m: float | None
    claims: SegmentClaims
    rasters: BlockRasters
    buildings: list[Building] | BuildingsOnDisk

    def keep_buildings(self, buildings: list[Building]) -> None:
        """A block's buildings, after those of the blocks before."""
        self.buildings.extend(buildings)


def plan_blocks(fusion_dir, block_m: float | None, margin_m: float, engine: Engine) -> BlockPlan:
    """The blocks of ``fusion_dir``'s grid (:func:`model_blocks`); the segments' numbers
    are kept in ``engine``'s task store when it has one."""
    grid, crs = fusion_header(fusion_dir)
    blocks, side_m = model_blocks(grid, block_m, margin_m)
    folder = engine.store.folder if engine.store is not None else None
    kept = BuildingsOnDisk(Path(folder) / "buildings") if folder and len(blocks) > 1 else []
    return BlockPlan(grid, blocks, side_m, SegmentClaims(grid, blocks, folder, crs),
                     BlockRasters(grid, blocks, fusion_dir, folder, crs), kept)  # fmt: skip


def kept_buildings(results: list) -> list[Building]:
    """The buildings of a block's task answers (those with a ``building``), taken out of
    them: :meth:`BlockPlan.keep_buildings` keeps them, the answers the rest."""
    out = [x.building for x in results if x.building is not None]
    for x in results:
        x.building = None
    return out


def each_block(blocks: list[Block]):
    """The blocks, with a progress bar (or a line a minute) when there are several."""
    return progress(blocks, "blocks") if len(blocks) > 1 else blocks


def block_engine(engine: Engine, blocks: list[Block], block: Block) -> Engine:
    """The engine a block's tasks run on: with several blocks, each keeps its finished
    tasks in a folder of its own (for --resume: its segments' numbers are its own)."""
    return engine if len(blocks) == 1 else engine.kept_in(engine.store, f"block_{block.index}")


def blocks_lines(record: dict | None) -> list[str]:
    """What a path prints of its :func:`blocks_record` (nothing for the whole grid)."""
    if not record:
        return []
    wide = record["segments_wider_than_the_margin"]
    return [f"  in {record['count']} blocks of {record['side_m']:g} m with "
            f"{record['margin_m']:g} m of margin"
            + (f"; {wide} wider than the margin, modelled in part" if wide else "")]  # fmt: skip


def blocks_record(blocks: list[Block], block_m: float, margin_m: float, wide: int) -> dict:
    """model.json's record of the blocks (``wide``: segments wider than the margin)."""
    return {"count": len(blocks), "side_m": round(block_m, 3), "margin_m": margin_m,
            "segments_wider_than_the_margin": wide}  # fmt: skip


class GridRaster:
    """A raster of the whole grid that a run writes, and reads back, block by block: in
    memory, or with ``folder`` in a file there (:class:`~workbench.raster.WindowedRaster`)
    so that no whole-grid array is held.

    Parameters
    ----------
    name : str
        The raster's name: ``NAME.tif`` in the run folder.
    grid : Grid
        The whole grid.
    dtype, nodata
        The raster's (``nodata`` also fills the cells not yet written).
    folder : path, optional
    crs : CRS, optional
    """

    def __init__(self, name: str, grid: Grid, dtype, nodata=None, folder=None, crs=None):
        self.name, self.grid, self.dtype, self.nodata = name, grid, np.dtype(dtype), nodata
        self.array: np.ndarray | None = None
        self.file = None
        if folder is not None:
            self.file = WindowedRaster(Path(folder) / f"{name}.tif", grid, crs, self.dtype,
                                       nodata=nodata)  # fmt: skip

    def read(self, rows: slice, cols: slice) -> np.ndarray:
        """(h, w) the cells as written so far (a view, in memory)."""
        if self.file is not None:
            return self.file.read(rows, cols)[0]
        return self._memory()[rows, cols]

    def write(self, data: np.ndarray, rows: slice, cols: slice) -> None:
        """``data`` (h, w) at the cells ``rows`` x ``cols``."""
        if self.file is not None:
            self.file.write(data, rows, cols)
        elif self.array is None and data.shape == self.grid.shape:
            self.array = data  # the whole grid at once: kept as it is, not copied
        else:
            self._memory()[rows, cols] = data

    def _memory(self) -> np.ndarray:
        if self.array is None:
            self.array = np.full(self.grid.shape, self.nodata or 0, self.dtype)
        return self.array

    def written(self) -> dict:
        """``ModelRun``'s ``rasters`` or ``raster_files`` entry of the raster."""
        if self.file is not None:
            self.file.close()
            return {"raster_files": {self.name: self.file.path}}
        return {"rasters": {self.name: (self._memory(), self.nodata)}}


def merged_outputs(*entries: dict) -> dict:
    """``ModelRun``'s ``rasters`` and ``raster_files`` from several :meth:`GridRaster.
    written` entries."""
    out = {"rasters": {}, "raster_files": {}}
    for entry in entries:
        for key, value in entry.items():
            out[key].update(value)
    return out


class SegmentClaims:
    """Which block models which segment, and the segments modelled so far as one raster.

    Parameters
    ----------
    grid : Grid
        The whole grid.
    blocks : list of Block
        In the order they are modelled (their inner cells tile the grid).
    folder : path, optional
        With several blocks, where the numbers are kept (``segments.tif``, written and
        read back block by block), so that no whole-grid array is held; else in memory.
    crs : CRS, optional
        The grid's, for ``segments.tif``.

    Attributes
    ----------
    grid : Grid
    ids : GridRaster
        The segments modelled so far, numbered on the whole grid; 0 elsewhere.
    count : int
        How many segments the blocks have given to be modelled.
    """

    def __init__(self, grid: Grid, blocks: list[Block], folder=None, crs=None):
        self.grid = grid
        self.whole = len(blocks) == 1
        # 4 bytes a cell: 2.5 GB for 100 km² at 0.4 m
        self.ids = GridRaster("segments", grid, np.int32, 0, None if self.whole else folder, crs)
        self.count = 0
        self._offset = 0  # the numbers of the segments of the blocks before
        self._row_starts = np.unique([b.inner[0].start for b in blocks])
        self._col_starts = np.unique([b.inner[1].start for b in blocks])
        self._index = {(b.inner[0].start, b.inner[1].start): b.index for b in blocks}

    def block_of(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Index of the block whose inner cells hold each cell (whole-grid rows, cols)."""
        r0 = self._row_starts[np.searchsorted(self._row_starts, rows, side="right") - 1]
        c0 = self._col_starts[np.searchsorted(self._col_starts, cols, side="right") - 1]
        return np.array([self._index[(int(a), int(b))] for a, b in zip(r0, c0, strict=True)],
                        np.int64)  # fmt: skip

    def segments_to_model(
        self, block: Block, segments: np.ndarray, q: int, boxes: np.ndarray, last: bool
    ) -> tuple[list[int], int]:
        """The segments (numbers 1..q of ``segments``, the block's outer cells) the block
        models, and how many of those its outer edge cuts.

        Before the ``last`` round (whose models stay), a block models every segment that
        its edge does not cut and whose ``boxes`` ((q + 1, 4) r0, r1, c0, c1 on the outer
        cells) reach its inner cells: their priors pull the next round's level set."""
        if self.whole:
            return list(range(1, q + 1)), 0
        cut = self._cut_segments(block, segments, q)
        if not last:
            (ir, ic), rr, cc = block.inside, boxes[:, :2], boxes[:, 2:]
            reach = (rr[:, 0] < ir.stop) & (rr[:, 1] > ir.start)
            reach &= (cc[:, 0] < ic.stop) & (cc[:, 1] > ic.start)
            return [k for k in range(1, q + 1) if reach[k] and not cut[k]], 0
        labels = segments.ravel()
        n = np.bincount(labels, minlength=q + 1).astype(np.float64)
        rows, cols = np.indices(segments.shape)
        centre_r = np.bincount(labels, rows.ravel(), q + 1) / np.maximum(n, 1)
        centre_c = np.bincount(labels, cols.ravel(), q + 1) / np.maximum(n, 1)
        taken = np.bincount(labels, (self.ids.read(*block.outer) > 0).ravel(), q + 1)
        r, c = block.origin
        owner = self.block_of(np.floor(centre_r[1:]).astype(int) + r,
                              np.floor(centre_c[1:]).astype(int) + c)  # fmt: skip
        todo, wide = [], 0
        for k in range(1, q + 1):
            j = owner[k - 1]
            if n[k] == 0 or taken[k] > 0.5 * n[k]:  # none here, or a block before modelled it
                continue
            if cut[k]:
                if j == block.index:  # wider than the margin: the part this block holds
                    todo.append(k)
                    wide += 1
            elif j <= block.index:  # its centre is here, or a block before missed it
                todo.append(k)
        if wide:
            log.warning("block %d: %d segment(s) wider than the blocks' margin, modelled "
                        "from the part the block holds", block.index, wide)  # fmt: skip
        return todo, wide

    def _cut_segments(self, block: Block, segments: np.ndarray, q: int) -> np.ndarray:
        """(q + 1,) bool: the segments on a side of the outer cells that cuts the grid."""
        north, south, west, east = block.cut_edges(self.grid.shape)
        edges = [segments[0] if north else (), segments[-1] if south else (),
                 segments[:, 0] if west else (), segments[:, -1] if east else ()]  # fmt: skip
        cut = np.zeros(q + 1, bool)
        for e in edges:
            cut[np.asarray(e, np.int64)] = True
        cut[0] = False
        return cut

    def claim(self, block: Block, segments: np.ndarray, q: int, todo: list[int]) -> np.ndarray:
        """Number the modelled segments ``todo`` (of 1..q in ``segments``) on the whole
        grid, and mark their cells not yet taken; returns (q + 1,) each segment's number
        (its own when the block is the whole grid; 0 for those not modelled)."""
        number = np.zeros(q + 1, np.int32)
        number[todo] = np.asarray(todo, np.int32) + self._offset
        here = self.ids.read(*block.outer)
        free = here == 0
        here[free] = number[segments[free]]
        self.ids.write(here, *block.outer)
        self._offset += q
        self.count += len(todo)
        return number


class BlockRasters:
    """What a run writes of the whole grid, from its blocks. With one block, that block's
    arrays as they are. With several, no whole-grid array: the DTM and the DSM stay the
    fusion's files (the model's DTM is the fusion's; each building's RMS to the DSM is
    read in its window), the path's own rasters are written block by block into files of
    ``folder`` (:class:`GridRaster`), the ground mesh is the blocks' pieces joined on a
    lattice of the whole grid, and the preview is drawn on a coarse mosaic of the ortho
    and the layers the path draws over it.

    Parameters
    ----------
    grid : Grid
        The whole grid.
    blocks : list of Block
    fusion_dir : path
        The fusion run the blocks read.
    folder : path, optional
        Where the path's own rasters are written with several blocks (else in memory).
    crs : CRS, optional
        The grid's.
    preview_cells : int
        The coarse mosaic's longest side, cells.
    """

    def __init__(self, grid: Grid, blocks: list[Block], fusion_dir, folder=None, crs=None,
                 preview_cells: int = 2048):  # fmt: skip
        self.grid, self.fusion_dir, self.crs = grid, Path(fusion_dir), crs
        self.whole = len(blocks) == 1
        self.folder = None if self.whole else folder
        self.arrays: dict[str, np.ndarray] = {}
        self.own: dict[str, GridRaster] = {}
        self.step = max(1, round(GROUND_CELL_M / grid.gsd))
        self.factor = max(1, -(-max(grid.shape) // preview_cells))
        f = self.factor
        self.coarse = Grid(grid.xmin, grid.ymax, grid.gsd * f, -(-grid.width // f),
                           -(-grid.height // f))  # fmt: skip
        # a piece's unknown heights: one value for every block, so that two pieces give
        # their shared vertices the same height
        self.fill = None
        if not self.whole:
            z = read_decimated(self.fusion_dir / "dtm.tif", preview_cells)
            self.fill = float(np.nanmedian(z)) if np.isfinite(z).any() else None
        # the ground's pieces: on disk with a folder, so that the writer streams them
        self.pieces: list[Surface] | SurfacePieces = []
        if self.folder is not None:
            (Path(self.folder) / "ground").mkdir(parents=True, exist_ok=True)
            self.pieces = SurfacePieces(Path(self.folder) / "ground")

    def put(self, block: Block, grid: Grid, *, dtm: np.ndarray, rgb: np.ndarray,
            dsm: np.ndarray | None = None, **layers: np.ndarray) -> None:  # fmt: skip
        """The block's arrays ((h, w) or (h, w, 3) on its outer cells, ``grid``): the DTM
        and the ortho, the DSM, and the ``layers`` the preview draws (a mask, classes)."""
        if self.whole:
            self.arrays.update(dtm=dtm, rgb=rgb, dsm=dsm, **layers)
            return
        rows, cols = (self._lattice(i, o) for i, o in zip(block.inner, block.outer,
                                                          strict=True))  # fmt: skip
        piece = ground_surface(dtm[rows, cols], rgb[rows, cols], grid.window(rows, cols),
                               self.fill)  # fmt: skip
        if piece is not None and isinstance(self.pieces, SurfacePieces):
            self.pieces.add(piece)
        elif piece is not None:
            self.pieces.append(piece)
        origin = (block.outer[0].start, block.outer[1].start)
        inside, at = decimated_cells(*block.inner, self.factor, origin)
        for name, a in {"rgb": rgb, **layers}.items():
            if name not in self.arrays:
                self.arrays[name] = np.zeros(self.coarse.shape + a.shape[2:], a.dtype)
            self.arrays[name][at] = a[inside]

    def keep(self, name: str, block: Block, data: np.ndarray, nodata=None) -> None:
        """The path's own raster ``name``.tif: ``data`` (h, w) on the block's outer cells,
        of which its inner ones are written."""
        if name not in self.own:
            self.own[name] = GridRaster(name, self.grid, data.dtype, nodata, self.folder,
                                        self.crs)  # fmt: skip
        self.own[name].write(data[block.inside], *block.inner)

    def _lattice(self, inner: slice, outer: slice) -> slice:
        """The cells (of the outer ones) of the ground's lattice rows (or columns) from the
        first at or after the inner ones' start to the first at or after their end: a
        block's piece meets the next one's on a shared row of vertices."""
        step = self.step
        a = -(-inner.start // step) * step
        b = -(-inner.stop // step) * step
        b = min(b, (outer.stop - 1) // step * step)
        return slice(a - outer.start, b - outer.start + 1)

    def ground(self) -> Surface | SurfacePieces | None:
        """The ground mesh of 2 m cells, coloured by the ortho (in pieces on disk, with
        several blocks and a folder)."""
        if self.whole:
            return ground_surface(self.arrays["dtm"], self.arrays["rgb"], self.grid)
        if isinstance(self.pieces, SurfacePieces):
            return self.pieces if self.pieces.files else None
        if not self.pieces:
            return None
        V, T, _ = concatenate_meshes([(p.vertices, p.triangles) for p in self.pieces])
        return Surface(V, T, vertex_colors=np.concatenate([p.vertex_colors for p in self.pieces]))

    def preview_layers(self) -> tuple[dict[str, np.ndarray], Grid]:
        """The ortho (``rgb``) and the layers put beside it, and their grid (the whole
        grid's, or the coarse mosaic's), for the preview."""
        layers = {k: v for k, v in self.arrays.items() if k not in ("dtm", "dsm")}
        return layers, self.grid if self.whole else self.coarse

    def model_rasters(self, segments: SegmentClaims | None = None) -> dict:
        """``ModelRun``'s ``dtm``, ``dsm``, ``rasters`` and ``raster_files`` for the run:
        the path's own rasters, and with ``segments`` their numbers as ``segments.tif``."""
        own = [r.written() for r in self.own.values()]
        if segments is not None:
            own.append(segments.ids.written())
        out = merged_outputs(*own)
        if self.whole:
            return {"dtm": self.arrays["dtm"], "dsm": self.arrays["dsm"], **out}
        out["raster_files"]["dtm"] = self.fusion_dir / "dtm.tif"
        return {"dtm": None, "dsm": RasterWindows(self.fusion_dir / "dsm.tif", self.grid), **out}
