"""A fusion larger than memory: the grid cut into blocks, each fused with a margin around
it, the inside of each written into windows of the output rasters.

The command's memory then follows the block, not the area: every whole-grid step of the
fusion (the ground filter, the class CRF, the planar objects, the crowns) runs on one
block and its margin at a time. The margin is the ground filter's largest window
(:data:`~fusion.ground.LARGEST_WINDOW_M`): a building cut by a block's edge is whole in
the block that keeps it, and the opening that takes it off the terrain sees all of it.
A cell's fused height and colour are those of its own observations, the same in any
block. What depends on the cells around can differ: the terrain interpolated under
buildings and crowns (the push-pull pyramid's cells fall elsewhere in a block), and
through it the elevation the forest learns from, the classes and the crowns' heights.

The forest is trained once, and every view classified once, over whole-grid rasters
(the DSM, DTM, surface heights and cues) that the blocks write inside themselves into
files on disk: the training and the classification are those of one grid, and the
classes do not change from one block to the next because a block holds fewer strokes.
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np

from workbench.engine import Engine, TaskStore, ThreadEngine, full_disk_named
from workbench.errors import WorkbenchError
from workbench.grid_blocks import Block, auto_block_size, block_layout
from workbench.progress import progress
from workbench.raster import Grid, raster_header
from workbench.records import StageTimer
from workbench.scene import Scene

from .geometry_cues import geometric_cues
from .grid_rasters import GridRasters
from .ground import LARGEST_WINDOW_M
from .options import FusionOptions
from .planar_objects import COUNTS as PLANAR_COUNTS
from .scene_fusion import (
    FusedSurface,
    ObservationCache,
    ViewContext,
    check_memory,
    classifies,
    classify_views,
    default_grid,
    depth_views,
    fused_ground,
    fused_heights,
    fused_products,
    run_figures,
    scratch_folder,
    training_strokes,
    view_forest,
    view_workers,
)

log = logging.getLogger(__name__)

PRODUCTS = ("ortho", "dsm", "dtm", "ndsm", "class_prob", "classes", "count")
SUMMED = ("tiles", "observations", "filled_cells", "rejected_isolated_spikes",
          *PLANAR_COUNTS, "crown_cells_raised", "crown_sightings_raised",
          "crown_sightings_cleared_beside_buildings")  # fmt: skip


def planned_grid(scene: Scene, opts: FusionOptions) -> Grid:
    """The grid :func:`~fusion.scene_fusion.fuse_views` will fuse on, known before it
    starts (for a scene without depth maps, the grid of its DSM by default)."""
    if (not any(v.depth_path is not None for v in scene.views) and scene.dsm is not None
            and opts.gsd is None and opts.bounds is None):  # fmt: skip
        g, _, _ = raster_header(scene.dsm, "dsm")
        opts = replace(opts, gsd=g.gsd, bounds=g.bounds)
    return default_grid(scene, opts)


GRID_FILE_BYTES = 22  # per cell: the whole-grid files (GridFiles.DTYPES) and 1 band of cues
OUTPUT_BYTES = 38  # per cell: the run's rasters, uncompressed, while they are written


def check_disk(grid: Grid, folder: Path) -> None:
    """Refuse, before any work, a grid in blocks whose files would not fit on the disk of
    ``folder`` (where the partial folder and the output go; its nearest existing parent)."""
    folder = Path(folder).absolute()
    while not folder.exists():
        folder = folder.parent
    need = grid.width * grid.height * (GRID_FILE_BYTES + OUTPUT_BYTES)
    free = shutil.disk_usage(folder).free
    if need > free:
        raise WorkbenchError(
            f"--gsd {grid.gsd:g}: a {grid.width} x {grid.height} grid in blocks needs about "
            f"{need / 2**30:.0f} GiB of disk for its rasters, more than the {free / 2**30:.0f}"
            f" GiB free in {folder}; use a larger --gsd or smaller --bounds"
        )


def block_size(grid: Grid, opts: FusionOptions) -> float | None:
    """The side of the fusion's blocks, metres: ``opts.block``; by default none (the
    whole grid at once) up to :data:`AUTO_BLOCK_CELLS` cells a side, else blocks of that
    many cells less their margins."""
    return opts.block if opts.block is not None else auto_block_size(grid, LARGEST_WINDOW_M)


def fuse_in_blocks(scene: Scene, opts: FusionOptions, engine: Engine | None, write,
                   block_m: float) -> tuple[Grid, dict, object]:  # fmt: skip
    """Fuse ``scene`` block by block; ``write(block, products)`` receives each block's
    products inside it, in block order.

    1. Each block (with its margin) is observed, its heights fused and its ground
       filtered; the inside of its DSM, DTM and cues goes into whole-grid files
       (:class:`GridFiles`).
    2. The forest is trained and every view classified once, over those files, as
       :func:`~fusion.scene_fusion.fuse_views` does over its grid's.
    3. Each block's colours, classes and crowns, from its observations and heights (kept
       in the task store by step 1) and the files' DSM and DTM over it.

    Parameters
    ----------
    scene : Scene
    opts : FusionOptions
    engine : Engine, optional
        Runs every block's tasks; with a store, each block's finished tasks and
        products are kept there for ``--resume``.
    write : callable
        ``write(block, products)``: ``products`` maps each name of :data:`PRODUCTS` to
        the block's inner cells (``ortho`` (h, w, 3) uint8, ``class_prob`` (4, h, w)
        float32, ``classes`` (h, w) uint8, ``count`` (h, w) int16, the heights (h, w)
        float32).
    block_m : float
        A block's side, metres.

    Returns
    -------
    the whole grid, the run's record, the forest (None without one)
    """
    timer = StageTimer()
    views, skipped, mode, given, opts = depth_views(scene, opts, timer)
    with timer.stage("grid"):
        grid = default_grid(scene, opts)
        blocks = block_layout(grid, block_m)
        for b in blocks:
            check_memory(grid.window(*b.outer), opts, len(views))
        engine = engine or ThreadEngine(view_workers(views, opts))
    with scratch_folder(engine) as folder:
        folder = Path(folder)
        # the third step takes the first one's observations and heights from the store
        store = engine.store or TaskStore(folder / "tasks")
        shared_views = engine.share(views)
        files = GridFiles(folder / "grid", grid)
        probs = folder / "probs"
        probs.mkdir(exist_ok=True)

        def heights(b: Block):
            """The block's observations and fused heights (kept in the store)."""
            sub = engine.kept_in(store, f"block{b.index}")
            cache = ObservationCache(folder / f"block{b.index}", grid.window(*b.outer),
                                     opts.tile, probs_folder=probs)  # fmt: skip
            cache.folder.mkdir(exist_ok=True)
            with timer.stage("observations"):
                cache.observe(sub, shared_views, len(views), opts.tolerance)
            with timer.stage("heights"):
                h = fused_heights(cache, sub)
            return sub, cache, h

        caches, levels = [], []
        for b in progress(blocks, "blocks' heights"):
            sub, cache, h = heights(b)
            caches.append(cache)
            if store.has("surfaces", str(b.index)):
                levels.append(store.load("surfaces", str(b.index)))
                continue
            with timer.stage("ground"):
                surface = fused_ground(h, cache.grid, mode, given, b.origin)
            levels.append(files.write(b, surface, h.spread, opts.geometry_cues))
            store.save("surfaces", str(b.index), levels[-1])
            del h, surface
        ctx = files.context(views, opts, levels) if classifies(scene, opts) else None
        with timer.stage("training"):
            forest, class_source = view_forest(scene, ctx, opts, engine)
        with timer.stage("classification"):
            n_px = classify_views(ViewsInBlocks(caches, probs), ctx, forest, engine)
        strokes = training_strokes(scene) if forest is not None and opts.flat_colours else None
        record = {"pixels_classified": n_px, **{k: 0 for k in SUMMED}}
        colours_fitted = 0
        for b in progress(blocks, "blocks"):
            (r, c) = b.inner
            log.info("block %d of %d: rows %d-%d, columns %d-%d", b.index + 1, len(blocks),
                     r.start, r.stop, c.start, c.stop)  # fmt: skip
            if store.has("blocks", str(b.index)):
                products, figures = store.load("blocks", str(b.index))
                log.info("block %d finished before, kept", b.index + 1)
            else:
                products, figures = _block_products(b, heights, files, shared_views, forest,
                                                    strokes, class_source, mode, opts,
                                                    timer)  # fmt: skip
                store.save("blocks", str(b.index), (products, figures))
            write(b, products)
            for k in SUMMED:
                record[k] += figures[k]
            colours_fitted += figures["flat_colours"]["used"]
            record["class_source"] = figures["class_source"]
    # each block fits ground's and grass's colours to its own window, margin included
    record["flat_colours"] = {"used": colours_fitted > 0, "blocks_fitted": colours_fitted,
                              "blocks": len(blocks)}  # fmt: skip
    grid_cells = grid.width * grid.height
    blocks_figures = {
        "count": len(blocks),
        "side_m": round(float(block_m), 3),
        "margin_m": LARGEST_WINDOW_M,
        # the work the margins add: every block's cells, margins included, over the grid's
        "cells_fused_per_cell": round(sum(_cells(b.outer) for b in blocks) / grid_cells, 3),
        "largest_block_cells": max(_cells(b.outer) for b in blocks),
    }
    record = run_figures(mode, views, skipped, engine, timer,
                         {"blocks": blocks_figures, **record}, forest)  # fmt: skip
    return grid, record, forest


def _block_products(b: Block, heights, files: GridFiles, shared_views, forest, strokes,
                    class_source, mode: str, opts: FusionOptions,
                    timer: StageTimer) -> tuple:  # fmt: skip
    """Step 3 on block ``b``: its products inside it, and their figures."""
    sub, cache, h = heights(b)
    dsm, dtm, dtm_full, spikes, holes = (files.read(name, b.outer) for name in SURFACE)
    h.count[spikes] = 0  # as the first step's ground filter left it
    s = FusedSurface(cache.grid, cache, h, dsm, dtm, dtm_full, spikes, holes, None, b.origin)
    result = fused_products(s, shared_views, forest, strokes, class_source, mode, opts, sub,
                            timer)  # fmt: skip
    del s, h
    inside = b.inside
    products = {
        "ortho": result.ortho[inside], "dsm": result.dsm[inside], "dtm": result.dtm[inside],
        "ndsm": result.ndsm[inside], "class_prob": result.class_prob[(slice(None), *inside)],
        "classes": result.classes[inside], "count": result.count[inside],
        "ceiling": result.ceiling[inside],
    }  # fmt: skip
    return {k: np.ascontiguousarray(v) for k, v in products.items()}, result.record


def _cells(window: tuple[slice, slice]) -> int:
    return (window[0].stop - window[0].start) * (window[1].stop - window[1].start)


SURFACE = ("dsm", "dtm", "dtm_full", "spikes", "holes")  # what fused_ground gives, in its order


class GridFiles:
    """The whole grid's DSM, DTM, cues and surface heights as ``.npy`` files that each
    block writes inside itself: what the views' features read
    (:class:`~fusion.grid_rasters.GridRasters`), and each block's DSM and DTM over its
    margin. A file is mapped only while a block writes or reads it, so that the
    command's memory holds no whole grid.

    Parameters
    ----------
    folder : path
    grid : Grid
        The whole grid.
    """

    DTYPES = {"dsm": np.float32, "dtm": np.float32, "dtm_full": np.float32, "spikes": bool,
              "holes": bool, "filled": np.float64}  # fmt: skip

    def __init__(self, folder: Path, grid: Grid):
        self.folder, self.grid = Path(folder), grid
        self.folder.mkdir(exist_ok=True)
        for name, dtype in self.DTYPES.items():
            self._create(name, dtype, grid.shape)

    def _create(self, name: str, dtype, shape: tuple) -> None:
        path = self.path(name)
        if path.exists():  # kept by an interrupted run, for --resume
            return
        np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=shape).flush()
        # the file's blocks taken now: a mapped write to a disk that is full would kill the
        # process (SIGBUS) rather than raise
        with full_disk_named(path, partial=path), open(path, "r+b") as f:
            os.posix_fallocate(f.fileno(), 0, path.stat().st_size)

    def path(self, name: str) -> Path:
        return self.folder / f"{name}.npy"

    def write(self, b: Block, surface: tuple, spread: np.ndarray, cues: bool) -> tuple:
        """Block ``b``'s :func:`~fusion.scene_fusion.fused_ground` arrays over its outer cells
        (and the geometric cues of its DSM and heights' ``spread``) written inside it;
        returns the median, lowest and highest height of its surface there."""
        inside = b.inside
        named = dict(zip(SURFACE, surface, strict=True))
        dsm, dtm_full = named["dsm"], named["dtm_full"]
        named["filled"] = np.where(np.isfinite(dsm), dsm, dtm_full).astype(np.float64)
        if cues:
            named["cues"] = geometric_cues(dsm, spread, self.grid.gsd)
            self._create("cues", np.float32, (len(named["cues"]), *self.grid.shape))
        for name, data in named.items():
            f = np.load(self.path(name), mmap_mode="r+")
            f[(..., *b.inner)] = data[(..., *inside)]
            f.flush()
            del f
        filled = named["filled"][inside]
        return float(np.nanmedian(filled)), float(np.nanmin(filled)), float(np.nanmax(filled))

    def read(self, name: str, window: tuple[slice, slice]) -> np.ndarray:
        """The file ``name`` at the cells ``window``, in memory."""
        f = np.load(self.path(name), mmap_mode="r")
        out = np.array(f[(..., *window)])
        del f
        return out

    def context(self, views, opts: FusionOptions, levels: list) -> ViewContext:
        """What the views' features need over the whole grid (``levels``: what
        :meth:`write` returned for each block)."""
        x0, y0, x1, y1 = self.grid.bounds
        median, low, high = np.array(levels).T
        origin = np.array([(x0 + x1) / 2, (y0 + y1) / 2, float(np.median(median))])
        names = ("dsm", "dtm", "filled") + (("cues",) if self.path("cues").exists() else ())
        rasters = GridRasters(self.grid, self.folder, names, origin, (low.min(), high.max()))
        return ViewContext(views, self.grid, opts, rasters)


class ViewsInBlocks:
    """The blocks' observation caches as one, for the views' classification: a view's
    observed pixels are those of every block, its probabilities in one folder."""

    def __init__(self, caches: list[ObservationCache], probs_folder: Path):
        self.caches, self.probs_folder = caches, probs_folder

    def view_pixels(self, i: int, n_pixels: int) -> np.ndarray:
        seen = np.zeros(n_pixels, bool)
        for c in self.caches:
            c.mark_view_pixels(i, seen)
        return np.flatnonzero(seen)

    def probs_path(self, i: int) -> Path:
        return self.probs_folder / f"{i}_probs.npy"
