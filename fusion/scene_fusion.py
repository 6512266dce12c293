"""Fusion of many calibrated views into ortho colour, height and class rasters.

Kluckner & Bischof (2010), sections 3 and 4: each view's depth map lifts its pixels
into the ortho grid; per cell the height is the median of the observations (weighted
toward steep rays: not in the paper), the colour the vector median, the class the
accumulated and normalised probabilities of a per-view random forest on Sigma Points
features.

Passes over the views (each reads a view's files once):

1. heights: lift, keep the visible surface per cell, weighted median -> DSM; ground
   filter -> DTM, nDSM;
2. training: Sigma Points of every view with the elevation cue from the DTM; the
   training strokes are projected into the views through their depth maps (so the
   forest learns from the same per-view features it will classify, facades of
   oblique views included);
3. classification and colour: per view, class probabilities of its pixels; where
   enough of a cell's observations are tree to their views, and lie well above its
   median, the DSM takes their height (:func:`~fusion.crowns.crown_sightings`: a
   crown's rim, whose ground the oblique views see); per cell, accumulated
   probabilities and the vector median colour of the top surface; the classes the
   nDSM contradicts damped; in and beside the tree cells, away from buildings, the DSM
   takes an upper quantile of the heights instead of their median
   (:func:`~fusion.crowns.crown_tops`).

The ortho grid is processed in tiles: a pass keeps only the current tile's
observations, so a worker's memory follows the tile size, not the area. Every pass is a
list of tasks, a view or a tile each, run by an engine (:mod:`workbench.engine`: a Dask
cluster, or threads of this process, as many as the cores and memory allow,
:func:`view_workers`); results are gathered in task order, so the products do not depend
on the engine or the number of workers.
"""

from __future__ import annotations

import copy
import logging
import os
import shutil
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from workbench.engine import Engine, ThreadEngine
from workbench.errors import InputError, WorkbenchError
from workbench.parallel import default_workers
from workbench.raster import Grid, class_codes, read_raster
from workbench.records import StageTimer, peak_memory_mb
from workbench.robust import (
    group_count,
    group_mean,
    group_weighted_quantile,
    vector_median,
)
from workbench.scene import Scene, View
from workbench.truth import sample_to_grid

from .class_crf import contrast_class_crf
from .classifier import (
    CLASSES,
    elevation_consistent,
    elevation_prior,
    load_classifier,
    predict_proba,
    train_forest,
)
from .crowns import (
    BENEATH_TOP_M,
    CROWN_QUANTILE,
    crown_sightings,
    crown_tops,
    sightings_clear_of_buildings,
)
from .dsm_depth import DsmSurface
from .flat_colours import weigh_by_stroke_colours
from .free_space import (
    FreeSpace,
    ceilings_and_free_space,
    relabel_grounded,
    relabel_porous,
    seen_through,
)
from .geometry_cues import cue_columns, geometric_cues
from .grid_rasters import GridRasters
from .ground import dtm_from_dsm
from .interpolate import fill_small_holes, push_pull_fill, small_holes
from .observations import (
    close_neighbours,
    grid_window,
    in_window,
    lift_depth,
    lift_pixels,
    observe,
    window_pixels,
)
from .options import FusionOptions
from .planar_objects import COUNTS as PLANAR_COUNTS
from .planar_objects import planar_roofs_classed_tree
from .raster_forest import classify_rasters, synthetic_raster_forest
from .sigma_points import MEAN_ELEVATION, N_FEATURES, feature_cues, sigma_points

log = logging.getLogger(__name__)

FEATURES = "sigma_points_lab_grad_elev_11x11_geometry_v2"
PAPER_FEATURES = "sigma_points_lab_grad_elev_11x11_v1"  # --no-geometry-cues


def feature_set(opts: FusionOptions) -> str:
    """The name of the per-view features the options give (a saved forest records it)."""
    return FEATURES if opts.geometry_cues else PAPER_FEATURES


HOLE_CELLS = 9  # holes up to this many cells are interpolated (and flagged -1 in count)
FILLED = -1
ELEVATION_MEDIAN = 5  # pixels, the median filter of the per-view elevation cue
FEATURE_BYTES_PER_PIXEL = 700  # peak of view_features, measured on small: 647


@dataclass
class FusionResult:
    grid: Grid
    ortho: np.ndarray  # (H, W, 3) uint8
    dsm: np.ndarray
    dtm: np.ndarray
    ndsm: np.ndarray
    class_prob: np.ndarray  # (4, H, W) float32, NaN where unseen
    count: np.ndarray  # (H, W) int16, -1 where interpolated
    ablation: dict = field(default_factory=dict)  # mean-fused colour and height
    record: dict = field(default_factory=dict)
    forest: object = None
    normal: np.ndarray | None = None  # (3, H, W) float32 unit normals, from a mesh
    class_map: np.ndarray | None = None  # (H, W) uint8 decided classes (the class CRF's and
    # planar objects'; a mesh's: its most probable class and planar objects')
    ceiling: np.ndarray | None = None  # (H, W) float32 over the cells no view saw, metres
    # (fusion.hidden_ceiling); None for a cloud's or a mesh's

    @property
    def classes(self) -> np.ndarray:
        """(H, W) uint8 class codes 1-4, 0 where unseen: the class CRF's labels where it
        ran (:mod:`fusion.class_crf`), else the most probable class of each cell."""
        return self.class_map if self.class_map is not None else class_codes(self.class_prob)


class DsmDepthView:
    """A view whose depth map is ray-cast from a DSM surface (computed once, kept)."""

    def __init__(self, view: View, surface: DsmSurface):
        self.view, self.surface = view, surface
        self.id, self.camera, self.image_path = view.id, view.camera, view.image_path
        self.depth_path = None
        self._depth = None

    def read_image(self) -> np.ndarray:
        return self.view.read_image()

    def read_depth(self) -> np.ndarray:
        if self._depth is None:
            self._depth = self.surface.depth_map(self.camera)
        return self._depth


def default_grid(scene: Scene, opts: FusionOptions) -> Grid:
    """The ortho grid: --bounds or the scene's bounds; --gsd or the scene's gsd or the
    nadir-most view's ground sampling distance."""
    bounds = opts.bounds or scene.bounds
    gsd = opts.gsd or scene.gsd
    views = [v for v in scene.views if v.depth_path is not None]
    if gsd is None or bounds is None:
        nadir = max(views, key=lambda v: -v.camera.viewing_direction[2])
        depth = nadir.read_depth()
        if gsd is None:
            gsd = float(np.nanmedian(depth)) / nadir.camera.K[0, 0]
        if bounds is None:
            xs, ys = [], []
            for v in views:
                _, xyz = lift_depth(v.camera, v.read_depth())
                xs += [xyz[:, 0].min(), xyz[:, 0].max()]
                ys += [xyz[:, 1].min(), xyz[:, 1].max()]
            bounds = (min(xs), min(ys), max(xs), max(ys))
    return Grid.from_bounds(*bounds, gsd)


def physical_memory() -> int:
    """This machine's physical memory, bytes."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def check_memory(grid: Grid, opts: FusionOptions, n_views: int) -> None:
    """Refuse a grid whose rasters would not fit in memory, before allocating."""
    cells = grid.width * grid.height
    tile_cells = min(cells, opts.tile * opts.tile)
    need = cells * 48 + tile_cells * 8 * min(n_views, 64) * 4  # rasters + a tile's observations
    total = physical_memory()
    if need > opts.max_memory_fraction * total:
        raise WorkbenchError(
            f"--gsd {grid.gsd:g}: a {grid.width} x {grid.height} grid needs about "
            f"{need / 2**30:.1f} GiB, more than {opts.max_memory_fraction:.0%} of this "
            f"machine's {total / 2**30:.0f} GiB; use a larger --gsd or smaller --bounds"
        )


def view_workers(views: list[View], opts: FusionOptions) -> int:
    """Views processed at once: ``opts.workers``, or as many as this process has cores
    and as half the machine's memory holds.

    A view's Sigma Points peak at about :data:`FEATURE_BYTES_PER_PIXEL` per pixel (the
    patch moments and their Cholesky factors), and every worker holds one view's.
    """
    largest = max((v.camera.width * v.camera.height for v in views), default=0)
    return workers_in_memory(opts, largest * FEATURE_BYTES_PER_PIXEL)


def workers_in_memory(opts: FusionOptions, task_bytes: float) -> int:
    """Tasks run at once: ``opts.workers``, or as many as this process has cores and as
    ``opts.max_memory_fraction`` of the machine's memory holds, each task peaking at
    ``task_bytes``."""
    if opts.workers is not None:
        return opts.workers
    fit = int(opts.max_memory_fraction * physical_memory() // max(task_bytes, 1))
    return max(1, min(default_workers(), fit))


def _joined(parts: list, dtype, tail: tuple = ()) -> np.ndarray:
    """The views' arrays of one tile end to end (an empty array of ``dtype`` for none)."""
    return np.concatenate(parts) if parts else np.zeros((0, *tail), dtype)


def tile_shape(grid: Grid, size: int) -> tuple[int, int]:
    """Rows and columns of the tiles of at most ``size`` x ``size`` cells that cut the
    grid most evenly: with a remainder tile, the workers would wait on the largest
    (`small`'s 800 cells a side: tiles of 400, not 512 and 288)."""
    return tuple(-(-n // -(-n // size)) for n in (grid.height, grid.width))


def _tiles(grid: Grid, size: int):
    th, tw = tile_shape(grid, size)
    for r0 in range(0, grid.height, th):
        for c0 in range(0, grid.width, tw):
            yield r0, c0, min(th, grid.height - r0), min(tw, grid.width - c0)


def preferred(cells: np.ndarray, reliable: np.ndarray, n_cells: int) -> np.ndarray:
    """(N,) bool: the observations a cell fuses: its reliable ones, or all of its
    visible ones where it has no reliable one (cells beside depth edges)."""
    has_reliable = np.bincount(cells[reliable], minlength=n_cells) > 0
    return reliable | ~has_reliable[cells]


def top_surface_votes(
    cells: np.ndarray,
    z: np.ndarray,
    reliable: np.ndarray,
    top: np.ndarray,
    beneath_m: float = BENEATH_TOP_M,
) -> np.ndarray:
    """(N,) bool: the observations that give a cell its colour and class votes.

    An orthophoto shows the top surface, yet under a crown's edge an oblique view sees
    the ground beneath it and would vote grass for a crown cell. A cell's votes are its
    reliable observations not more than ``beneath_m`` below its top surface, or, where
    it has none, all of its visible ones not below that (:func:`preferred`; the
    top of a crown's rim is seen in steep points only). On small seeds 0, 1 and 2
    the tree accuracy of the fused classes rose from 0.80, 0.78 and 0.78 to 0.84, 0.82
    and 0.84 (1 m and 2 m scored alike).

    Parameters
    ----------
    cells : (N,) int64 cell index of each observation
    z : (N,) float heights, metres
    reliable : (N,) bool
    top : (n_cells,) float the cells' top surface (an upper quantile of their heights,
        or the crown the views see over them), metres, NaN unknown (no limit)
    beneath_m : float
    """
    above = z >= np.nan_to_num(top, nan=-np.inf)[cells] - beneath_m
    return preferred(cells, reliable & above, len(top)) & above


def elevation_image(obs_pixels, xyz, shape, dtm: np.ndarray, grid: Grid) -> np.ndarray:
    """(H, W) elevation above the DTM of the surface each pixel sees, metres.

    Pixels without a depth take the pyramid interpolation of their neighbours'. A 5 x 5
    median removes the isolated gross errors of dense matching: one of them in an
    11 x 11 patch gives flat ground the elevation variance of a tree crown.
    """
    r, c = grid.cell_index(xyz[:, 0], xyz[:, 1], clip=True)
    elev = np.full(shape[0] * shape[1], np.nan)
    elev[obs_pixels] = xyz[:, 2] - dtm[r, c]
    elev = elev.reshape(shape)
    valid = np.isfinite(elev)
    if not valid.any():
        return np.zeros(shape, np.float32)
    filled = push_pull_fill(elev, valid).astype(np.float32)
    return cv2.medianBlur(filled, ELEVATION_MEDIAN)


def view_features(
    view: View, rgb, depth, dtm, grid, patch, surface=None, cues=None, window=None, only=None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lifted pixels of a view, their points and their features: Sigma Points
    (78), with the geometric cues of each pixel's cell after them when ``cues``
    (G, H, W) are given (:mod:`fusion.geometry_cues`).

    Pixels without a matched depth take it from the fused ``surface`` (a
    :class:`~fusion.dsm_depth.DsmSurface`) for their elevation cue: the interpolation
    of their neighbours would lift a shadow beside a tower to the tower's height. They
    have no point, so no row of their own.

    With ``window`` (rows, columns), the lifted pixels in it, as flat indices in it: the
    elevation is interpolated over the whole image, the patches read the window alone.
    With ``only``, (M,) sorted flat indices in the whole image or a function of the lifted
    pixels and their points that returns which to keep ((N,), (N, 3) -> (N,) bool), those
    pixels alone: their features are those they have among all.

    Returns
    -------
    feats : (N, 78 [+ G]) float32
        Row k the features of pixel ``pixels[k]``.
    pixels : (N,) int
        Flat indices of the lifted pixels (in the window, with ``window``).
    xyz : (N, 3) float
        Their points, world metres.
    """
    pixels, xyz = lift_depth(view.camera, depth)
    all_pixels, all_xyz = pixels, xyz
    if surface is not None and len(pixels) < depth.size:
        unknown = np.flatnonzero(~np.isfinite(depth))  # a few hundredths of the pixels
        d = surface.depth_at(view.camera, unknown)
        with np.errstate(invalid="ignore"):
            hit = d > 0  # False where the ray misses (NaN)
        unknown, d = unknown[hit], d[hit]
        # only the filled pixels are lifted again: the elevation image scatters its points
        all_pixels = np.concatenate([pixels, unknown])
        all_xyz = np.concatenate([xyz, lift_pixels(view.camera, unknown, d, depth.shape[1])])
    elev = elevation_image(all_pixels, all_xyz, depth.shape, dtm, grid)
    if only is not None:
        keep = only(pixels, xyz) if callable(only) else np.isin(pixels, only, assume_unique=True)
        pixels, xyz = pixels[keep], xyz[keep]
    if window is not None:
        rgb, elev = rgb[window], elev[window]
        pixels, xyz = in_window(window, depth.shape, pixels, xyz)
    n_cues = 0 if cues is None else len(cues)
    feats = np.empty((len(pixels), N_FEATURES + n_cues), np.float32)
    sigma_points(feature_cues(rgb, elev), patch, pixels=pixels, out=feats)
    if cues is not None:
        feats[:, N_FEATURES:] = cue_columns(cues, xyz, grid)
    return feats, pixels, xyz


def fuse_views(
    scene: Scene, opts: FusionOptions | None = None, engine: Engine | None = None
) -> FusionResult:
    """Fuse the views of a scene into ortho rasters.

    Views with depth maps are lifted through them; views without one are skipped
    with a warning. A scene whose views have no depth map but which has a DSM gets
    a true orthophoto: each view's depth is ray-cast from the DSM.

    Parameters
    ----------
    scene : Scene
    opts : FusionOptions
    engine : Engine, optional
        Runs the views' and tiles' tasks (:mod:`workbench.engine`); its store keeps the
        finished ones for ``--resume``. Default: threads of this process
        (:func:`view_workers`), nothing kept.

    Returns
    -------
    FusionResult
    """
    opts = opts or FusionOptions()
    timer = StageTimer()
    views, skipped, mode, given, opts = depth_views(scene, opts, timer)
    with timer.stage("grid"):
        grid = default_grid(scene, opts)
        check_memory(grid, opts, len(views))
        engine = engine or ThreadEngine(view_workers(views, opts))
    with scratch_folder(engine) as folder:
        shared_views = engine.share(views)
        s = fused_surface(views, shared_views, grid, mode, given, opts, engine, folder, timer,
                          with_context=classifies(scene, opts))  # fmt: skip
        with timer.stage("training"):
            forest, class_source = view_forest(scene, s.context, opts, engine)
        with timer.stage("classification"):
            n_px = classify_views(s.cache, s.context, forest, engine)
        strokes = training_strokes(scene) if forest is not None and opts.flat_colours else None
        result = fused_products(s, shared_views, forest, strokes, class_source, mode, opts,
                                engine, timer)  # fmt: skip
        result.record["pixels_classified"] = n_px
    result.record = run_figures(mode, views, skipped, engine, timer, result.record, forest)
    return result


def run_figures(mode: str, views, skipped, engine: Engine, timer: StageTimer, figures: dict,
                forest) -> dict:  # fmt: skip
    """The fusion's record: its mode, views and engine, ``figures`` (the products',
    ``observations`` and ``pixels_classified`` among them), the stages' times and
    memory, and the throughputs."""
    stages = timer.stages
    observing_s = stages["observations"]["wall_s"] + stages["heights"]["wall_s"]
    record = {
        "mode": mode,
        "views": {"used": len(views), "skipped_no_depth": len(skipped), "skipped_ids": skipped},
        "workers": engine.workers,
        **engine.describe(),
        **figures,
        "stages": stages,
        "observations_per_s": round(figures["observations"] / max(observing_s, 1e-9)),
        "peak_memory_mb": round(peak_memory_mb(), 1),
    }
    if forest is not None and stages["classification"]["wall_s"] > 0:
        record["classification_mpx_per_s"] = round(
            figures["pixels_classified"] / 1e6 / stages["classification"]["wall_s"], 3
        )
    return record


def classifies(scene: Scene, opts: FusionOptions) -> bool:
    """Whether the views are classified (a forest given or trained on the scene's
    strokes): their features need the fused rasters in files."""
    return opts.classifier is not None or scene.training_labels is not None


@dataclass
class FusedSurface:
    """The heights pass over a grid: what its colour pass and classes build on.

    ``dsm`` has its isolated spikes dropped and small holes filled, ``dtm`` is NaN where
    the DSM is, ``dtm_full`` defined everywhere; ``context`` is what a view's features
    need (None when the views are not classified); ``origin`` the (row, col) of the
    grid's first cell in the whole grid, when it is a block's (for the holes' fill)."""

    grid: Grid
    cache: ObservationCache
    heights: FusedHeights
    dsm: np.ndarray
    dtm: np.ndarray
    dtm_full: np.ndarray
    spikes: np.ndarray
    holes: np.ndarray
    context: ViewContext | None
    origin: tuple[int, int] = (0, 0)


def fused_surface(views, shared_views, grid: Grid, mode: str, given, opts: FusionOptions,
                  engine: Engine, folder: Path, timer: StageTimer, *,
                  with_context: bool) -> FusedSurface:  # fmt: skip
    """Pass 1 of the fusion (the module's docstring) on ``grid``: the views observed into
    ``folder``, their heights fused, the ground filtered, and the rasters the views'
    features read written beside them (``with_context``). ``shared_views`` is the
    engine's handle on ``views``."""
    cache = ObservationCache(folder, grid, opts.tile)
    with timer.stage("observations"):
        cache.observe(engine, shared_views, len(views), opts.tolerance)
    with timer.stage("heights"):
        h = fused_heights(cache, engine)
    with timer.stage("ground"):
        dsm, dtm, dtm_full, spikes, holes = fused_ground(h, grid, mode, given)
    ctx = None
    if with_context:
        # the surface that gives shadowed pixels their elevation cue: where no view saw the
        # top surface (beside towers, in their shadows) the ground is the better guess
        surface = DsmSurface(np.where(np.isfinite(dsm), dsm, dtm_full), grid)
        cues = geometric_cues(dsm, h.spread, grid.gsd) if opts.geometry_cues else None
        rasters = GridRasters.write(folder, grid, surface, dsm=dsm, dtm=dtm, cues=cues)
        ctx = ViewContext(views, grid, opts, rasters)
    return FusedSurface(grid, cache, h, dsm, dtm, dtm_full, spikes, holes, ctx)


def fused_products(s: FusedSurface, shared_views, forest, strokes, class_source, mode: str,
                   opts: FusionOptions, engine: Engine,
                   timer: StageTimer) -> FusionResult:  # fmt: skip
    """Pass 3 of the fusion on ``s.grid``, the views classified (:func:`classify_views`)
    by ``forest`` (or None), ground and grass weighed by the colours of the ortho under
    the training ``strokes`` (:func:`training_strokes`, or None): the colour pass, the
    classes and the crowns' corrections, and the ceiling over the cells no view saw.
    The result's record holds the figures of these products; the caller adds the run's."""
    test_free_space = mode == "depth maps" and opts.free_space
    with timer.stage("ceiling"):
        free = ceilings_and_free_space(engine, shared_views, len(s.cache.present), s.grid, s.dsm,
                                       s.dtm_full, opts.tolerance, test_free_space)  # fmt: skip
    ceiling = free.ceiling
    with timer.stage("colour_and_class"):
        c = colours_and_classes(s.cache, shared_views, forest is not None, s.dsm, s.heights,
                                mode, opts, engine)  # fmt: skip
    h = s.heights
    dsm, from_ground = s.dsm, np.zeros(s.grid.shape, bool)
    carved = porous = from_ground
    if test_free_space:
        with timer.stage("free_space_heights"):
            dsm, carved, from_ground, porous = under_free_space(
                s, c, free, engine, opts.tolerance, opts.label_split
            )
        if class_source is not None:  # None: the views are not classified
            class_source += (
                "; objects above the ground that the views see through at most of their "
                "cells made tree (fusion.free_space; counted in porous_objects_made_tree_cells)"
            )
    dsm, ndsm, class_prob, classes, ortho, count16, crowns, cleared, planar, flat, class_source = (
        _finish(c, h, dsm, s.dtm, s.spikes, s.holes, forest, strokes, class_source, s.grid,
                mode, opts, timer, engine, s.origin)
    )  # fmt: skip
    count16[from_ground] = FILLED
    record = {
        "tiles": len(s.cache.tiles),
        "observations": int(h.n_obs),
        "class_source": class_source,
        "filled_cells": int(s.holes.sum()),
        "rejected_isolated_spikes": int(s.spikes.sum()),
        **planar,
        "flat_colours": flat,
        "crown_cells_raised": int(crowns.sum()),
        "crown_sightings_raised": int((np.isfinite(c.crown_z) & ~cleared).sum()),
        "crown_sightings_cleared_beside_buildings": int(cleared.sum()),
        "hidden_cells": int(np.isfinite(ceiling).sum()),
        "seen_through_cells_lowered": int(carved.sum()),
        "seen_through_cells_from_ground": int(from_ground.sum()),
        "porous_objects_made_tree_cells": int(porous.sum()),
    }
    ablation = {"dsm_mean": h.dsm_mean, "ortho_mean": c.ortho_mean}
    ceiling[np.isfinite(dsm)] = np.nan  # the crowns' corrections fill a few
    return FusionResult(s.grid, ortho, dsm, s.dtm, ndsm, class_prob, count16, ablation, record,
                        forest, class_map=classes, ceiling=ceiling)  # fmt: skip


def under_free_space(s: FusedSurface, c: FusedColours, free: FreeSpace, engine: Engine,
                     tolerance: float, label_split: float):  # fmt: skip
    """The DSM kept under the free space the views see (:mod:`fusion.free_space`), and the
    accumulated class probabilities of the objects the views see through made tree.

    ``free`` is :func:`~fusion.free_space.ceilings_and_free_space`'s. A
    cell :func:`~fusion.free_space.seen_through` contradicts, where the views that see
    past it are not fewer than those with a trusted observation above its free space
    (a crown classed building is seen from above by many more views than see beneath its
    canopy), takes the weighted median of its observations at or below the free space
    (:func:`heights_under`), the ground (``s.dtm_full``) where it has none; in the porous
    objects tree and each cell's most probable class trade places in ``c.prob_sum`` (in
    place), and so do the more probable of ground and grass in the lowered cells now
    within half the ``label_split`` (metres) of the ground
    (:func:`~fusion.free_space.relabel_grounded`).

    Returns the DSM (a new array), and the (H, W) bool cells lowered, those of them
    that took the ground, and those made tree.
    """
    sums = c.prob_sum
    with np.errstate(invalid="ignore"):
        elevated = np.isfinite(s.dsm) & (s.dsm - s.dtm_full > tolerance)
    candidates, porous = seen_through(free.lowest, sums, elevated & ~np.isfinite(c.crown_z))
    median, views_above = heights_under(s.cache, engine,
                                        np.where(candidates, free.lowest, np.nan))  # fmt: skip
    # the views that see past a point are evidence it is empty, as those that put a
    # surface there are that it is not: the free space holds unless it is outnumbered
    lowered = candidates & (free.views >= views_above)
    from_ground = lowered & ~np.isfinite(median)
    dsm = s.dsm.copy()
    dsm[lowered] = np.where(from_ground, s.dtm_full, median)[lowered]
    relabel_porous(sums, porous)
    with np.errstate(invalid="ignore"):
        relabel_grounded(sums, lowered & (dsm - s.dtm_full < label_split / 2))
    return dsm, lowered, from_ground, porous


def heights_under(cache: ObservationCache, engine: Engine,
                  cap: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Where ``cap`` ((H, W) metres) is known: (H, W) float32 the weighted median height
    of the cell's trusted observations at or below it (NaN where none is), and (H, W)
    int32 how many views have a trusted observation above it; NaN and 0 elsewhere. A
    task per tile that holds such a cell."""
    median = np.full(cache.grid.shape, np.nan, np.float32)
    above = np.zeros(cache.grid.shape, np.int32)
    tiles = [t for t, (r0, c0, h, w) in enumerate(cache.tiles)
             if np.isfinite(cap[r0 : r0 + h, c0 : c0 + w]).any()]  # fmt: skip
    results = engine.map(tile_heights_under, tiles, cache, cap, stage="free_space_heights")
    for t, (m, n) in zip(tiles, results, strict=True):
        r0, c0, h, w = cache.tiles[t]
        median[r0 : r0 + h, c0 : c0 + w], above[r0 : r0 + h, c0 : c0 + w] = m, n
    return median, above


def tile_heights_under(t: int, cache: ObservationCache, cap: np.ndarray) -> tuple:
    """Task: tile ``t``'s (h, w) parts of :func:`heights_under`."""
    r0, c0, h, w = cache.tiles[t]
    cap = cap[r0 : r0 + h, c0 : c0 + w].ravel()
    above = np.zeros(h * w, np.int32)
    kept = []
    for i in cache.touching(t):
        cells, z, weight, top = cache.in_tile(i, t, "cells", "z", "weight", "top")
        cells, z, weight = cells[top], z[top], weight[top]
        limit = cap[cells]
        below = z <= limit  # NaN caps compare False
        kept.append((cells[below], z[below], weight[below]))
        above[np.unique(cells[z > limit])] += 1
    cells, z, weight = (_joined([k[j] for k in kept], dtype)
                        for j, dtype in enumerate((np.int64, np.float32, np.float32)))  # fmt: skip
    (median,) = group_weighted_quantile(cells, z, weight, h * w, (0.5,))
    return median.reshape(h, w).astype(np.float32), above.reshape(h, w)


@contextmanager
def scratch_folder(engine: Engine):
    """The folder of the views' observations and probabilities: in the engine's store
    (kept for --resume; on a cluster, on a file system every worker sees), else a
    temporary folder of this machine (workers on it only)."""
    if engine.store is not None:
        yield engine.store.scratch("views")
        return
    folder = Path(tempfile.mkdtemp(prefix="fusion-"))
    try:
        yield folder
    finally:
        remove_folder(folder)


def remove_folder(folder: Path, tries: int = 20, pause_s: float = 0.25) -> None:
    """Remove the scratch ``folder``. When a task failed, its siblings already running
    on the workers are not stopped by their cancellation and may write a file into it
    while it is removed; they fail once it is gone (no task creates it), so a few tries
    apart remove it; one left behind is named in a warning, not an error hiding the
    task's."""
    for _ in range(tries):
        shutil.rmtree(folder, ignore_errors=True)
        if not folder.exists():
            return
        time.sleep(pause_s)
    log.warning("%s: could not remove this scratch folder; remove it by hand", folder)


@dataclass
class ViewContext:
    """What a view's features need, shared by the tasks of the training and the
    classification: the views, the grid, the options, the fused DSM and DTM, the surface
    that fills unmatched pixels and the geometric cues (in files a task reads the cells
    it needs of: :class:`~fusion.grid_rasters.GridRasters`), and the forest once
    trained."""

    views: list
    grid: Grid
    opts: FusionOptions
    rasters: GridRasters
    forest: object = None

    def features(self, v, seeing: Grid, only=None) -> tuple:
        """The view's depth map, and the lifted pixels' features (Sigma Points and cues),
        the lifted pixels and their points in the window of its pixels that see the grid
        ``seeing`` (:func:`~fusion.observations.grid_window`, :func:`view_features`;
        those ``only`` names alone if given), and the window; None for each but the depth
        where no pixel does."""
        depth = v.read_depth()
        window = grid_window(depth, v.camera, seeing, feature_margin(self.opts.patch))
        if window is None:
            return depth, None, None, None, None
        r = self.rasters
        feats, pixels, xyz = view_features(
            v, v.read_image(), depth, r.read("dtm"), self.grid, self.opts.patch, r.surface(),
            r.read("cues"), window, only,
        )  # fmt: skip
        return depth, feats, pixels, xyz, window


def feature_margin(patch: int) -> int:
    """Pixels the Sigma Points of ``patch`` x ``patch`` read around a pixel: half the
    patch, and one for the derivatives' Sobel kernel."""
    return patch // 2 + 1


def depth_views(scene: Scene, opts: FusionOptions, timer: StageTimer):
    """The views to fuse (with depth maps, or ray-cast from the scene's DSM), the ids of
    those skipped, the mode, the given DSM (or None) and the options (the DSM's grid by
    default in the true-orthophoto mode)."""
    views = [v for v in scene.views if v.depth_path is not None]
    skipped = [v.id for v in scene.views if v.depth_path is None]
    mode, given = "depth maps", None
    if not views and scene.dsm is not None and scene.views:
        with timer.stage("dsm_surface"):
            dsm_in, dsm_grid, _ = read_raster(scene.dsm, field="dsm", as_float=True)
            if opts.gsd is None and opts.bounds is None:
                opts = replace(opts, gsd=dsm_grid.gsd, bounds=dsm_grid.bounds)
            given = (dsm_in, dsm_grid)
            surface = DsmSurface(dsm_in[0].astype(np.float64), dsm_grid)
        views = [DsmDepthView(v, surface) for v in scene.views]
        skipped, mode = [], "true orthophoto (depth ray-cast from the scene's DSM)"
    if views and skipped:
        log.warning("%d view(s) without a depth map skipped: %s", len(skipped), ", ".join(skipped))
    check_height_source(scene)
    return views, skipped, mode, given, opts


def check_height_source(scene: Scene) -> None:
    """A one-line error unless some view has a depth map or the scene gives a DSM to
    ray-cast: called before any worker starts, so that bad input stops at once."""
    if not any(v.depth_path is not None for v in scene.views) and (
        scene.dsm is None or not scene.views
    ):
        raise InputError(
            scene.scene_json,
            "images",
            "no view has a depth map, and no DSM or point cloud is given",
        )


class ObservationCache:
    """Each view observed once (:func:`~fusion.observations.observe`), its visible
    observations kept on disk, split by tile, for the passes over the tiles.

    Per view and tile, ``<view>_<tile>.npz``: the cell index inside the tile (int32),
    height (float32), height weight (float32), top-surface flag (bool) and flat pixel
    index in the view (int32). ``present[i]`` lists the tiles view ``i`` reaches.
    """

    FIELDS = ("cells", "z", "weight", "top", "pixels")

    def __init__(self, folder: Path, grid: Grid, tile: int, probs_folder: Path | None = None):
        self.folder, self.grid, self.tile = folder, grid, tile
        # the views' class probabilities: beside the observations, or shared by the caches
        # of every block (fusion.blocks)
        self.probs_folder = probs_folder or folder
        self.tiles = list(_tiles(grid, tile))
        self.present: list[list[int]] = []

    def observe(self, engine: Engine, views, n_views: int, tolerance: float) -> None:
        """Observe every view (a task each); ``views`` is the engine's handle on them."""
        self.present = list(engine.map(observe_view, range(n_views), views, self, tolerance,
                                       stage="observations"))  # fmt: skip

    def tile_of(self, r: np.ndarray, c: np.ndarray) -> np.ndarray:
        th, tw = tile_shape(self.grid, self.tile)
        return (r // th) * -(-self.grid.width // tw) + c // tw

    def path(self, i: int, t: int) -> Path:
        return self.folder / f"{i}_{t}.npz"

    def probs_path(self, i: int) -> Path:
        """View ``i``'s class probabilities per pixel (:func:`classify_view`)."""
        return self.probs_folder / f"{i}_probs.npy"

    def touching(self, t: int) -> list[int]:
        """The views with observations in tile ``t``, in view order."""
        return [i for i, tiles in enumerate(self.present) if t in tiles]

    def view_pixels(self, i: int, n_pixels: int) -> np.ndarray:
        """(M,) int64 sorted flat indices of the pixels of view ``i`` (of ``n_pixels``)
        with an observation."""
        return np.flatnonzero(self.mark_view_pixels(i, np.zeros(n_pixels, bool)))

    def mark_view_pixels(self, i: int, seen: np.ndarray) -> np.ndarray:
        """``seen`` ((n_pixels,) bool) set at the pixels of view ``i`` with an observation
        (marked rather than sorted: several tiles, or blocks, observe a pixel)."""
        for t in self.present[i]:
            with np.load(self.path(i, t)) as f:
                seen[f["pixels"]] = True
        return seen

    def in_tile(self, i: int, t: int, *names: str) -> tuple:
        """View ``i``'s observations in tile ``t``: the fields ``names``."""
        with np.load(self.path(i, t)) as f:
            return tuple(f[n].astype(np.int64) if n in ("cells", "pixels") else f[n] for n in names)


def observe_view(i: int, views: list, cache: ObservationCache, tolerance: float) -> list[int]:
    """Task: observe view ``i`` and write its visible observations per tile; returns the
    tiles it reaches."""
    v, grid = views[i], cache.grid
    obs = observe(v.camera, v.read_depth(), grid, tolerance=tolerance)
    vis = np.flatnonzero(obs.visible)
    r, c = np.divmod(obs.cells[vis], grid.width)
    tile = cache.tile_of(r, c)
    order = np.argsort(tile, kind="stable")  # keeps the view's order within a cell
    tile, r, c, take = tile[order], r[order], c[order], vis[order]
    fields = {
        "z": obs.xyz[take, 2].astype(np.float32),
        "weight": obs.height_weight[take],
        "top": obs.top_surface[take],
        "pixels": obs.pixels[take].astype(np.int32),
    }
    present, starts = np.unique(tile, return_index=True)
    ends = np.append(starts[1:], len(tile))[: len(starts)]  # none for a view that sees nothing
    for t, a, b in zip(present.tolist(), starts, ends, strict=True):
        r0, c0, _, w = cache.tiles[t]
        cells = ((r[a:b] - r0) * w + (c[a:b] - c0)).astype(np.int32)
        np.savez(cache.path(i, t), cells=cells, **{k: f[a:b] for k, f in fields.items()})
    return present.tolist()


@dataclass
class FusedHeights:
    """The heights pass: (H, W) float32 weighted median, mean, CROWN_QUANTILE and
    interquartile range of each cell's trusted observations (NaN unseen), their count,
    and the number fused."""

    dsm: np.ndarray
    dsm_mean: np.ndarray
    dsm_upper: np.ndarray
    spread: np.ndarray
    count: np.ndarray
    n_obs: int


def fused_heights(cache: ObservationCache, engine: Engine) -> FusedHeights:
    """Section 3's median height per cell (weighted toward steep rays), a task per tile;
    the upper quantile is kept for :func:`~fusion.crowns.crown_tops`, which needs the
    classes first, and the interquartile range for the classifier's geometric cues."""
    grid = cache.grid
    out = FusedHeights(
        *(np.full(grid.shape, np.nan, np.float32) for _ in range(4)),
        np.zeros(grid.shape, np.int32), 0,
    )  # fmt: skip
    results = engine.map(tile_heights, range(len(cache.tiles)), cache, stage="heights")
    for (r0, c0, h, w), (median, mean, upper, spread, count, n) in zip(
        cache.tiles, results, strict=True
    ):
        window = (slice(r0, r0 + h), slice(c0, c0 + w))
        out.dsm[window], out.dsm_mean[window], out.dsm_upper[window] = median, mean, upper
        out.spread[window], out.count[window] = spread, count
        out.n_obs += n
    return out


def tile_heights(t: int, cache: ObservationCache) -> tuple:
    """Task: tile ``t``'s (h, w) median, mean, upper quantile and interquartile range of
    the trusted heights, their count, and the number of observations fused."""
    _, _, h, w = cache.tiles[t]
    parts = [cache.in_tile(i, t, "cells", "z", "weight", "top") for i in cache.touching(t)]
    cells, z, weight, rel = (
        _joined([p[k] for p in parts], dtype)
        for k, dtype in enumerate((np.int64, np.float32, np.float32, bool))
    )
    cells, z, weight = cells[rel], z[rel], weight[rel]
    # the median, the quartiles and the upper quantile from one sort
    q1, median, q3, upper = group_weighted_quantile(
        cells, z, weight, h * w, (0.25, 0.5, 0.75, CROWN_QUANTILE)
    ).reshape(4, h, w)
    mean = group_mean(cells, z, h * w).reshape(h, w)
    count = group_count(cells, h * w).reshape(h, w).astype(np.int32)
    f32 = np.float32
    return median.astype(f32), mean.astype(f32), upper.astype(f32), (q3 - q1).astype(f32), \
        count, len(z)  # fmt: skip


def fused_ground(h: FusedHeights, grid: Grid, mode: str, given,
                 origin: tuple[int, int] = (0, 0)):  # fmt: skip
    """The DSM with its isolated spikes dropped and small holes filled (or the given DSM
    on the grid), the DTM under it (NaN where the DSM is), the DTM everywhere, the spikes
    and the holes. ``origin``: (row, col) of the grid's first cell in the whole grid, when
    it is a block's: a hole is filled as the whole grid fills it
    (:func:`~.interpolate.fill_small_holes`)."""
    if mode == "depth maps":
        spikes = isolated_spikes(h.dsm, h.count)
        dsm = np.where(spikes, np.float32(np.nan), h.dsm)
        h.count[spikes] = 0
    else:  # the DSM is an input: it is the height product as it is
        dsm = sample_to_grid(given[0], given[1], grid)[0].astype(np.float32)
        spikes = np.zeros(grid.shape, bool)
    holes = small_holes(~np.isfinite(dsm), HOLE_CELLS)
    dsm = fill_small_holes(dsm, np.isfinite(dsm), holes, HOLE_CELLS, origin)
    dtm_full, _ = dtm_from_dsm(dsm, grid.gsd, origin=origin)
    dtm = np.where(np.isfinite(dsm), dtm_full, np.nan).astype(np.float32)
    return dsm, dtm, dtm_full, spikes, holes


def view_forest(scene: Scene, ctx: ViewContext | None, opts: FusionOptions, engine: Engine):
    """Section 4's per-view forest, loaded or trained on the scene's strokes (None
    without either), and a sentence on where it came from."""
    if opts.classifier is not None:
        forest, _ = load_classifier(opts.classifier, features=feature_set(opts))
        return forest, f"classifier file {opts.classifier}"
    if scene.training_labels is None:
        return None, None
    forest, n_train, n_dropped = _train(ctx, scene.training_labels, engine)
    name = Path(scene.training_labels).name
    return forest, (
        f"forest trained on {n_train} pixels of {name} projected into the views "
        f"({n_dropped} labelled pixels dropped: their elevation contradicts their class)"
    )


def training_strokes(scene: Scene) -> tuple | None:
    """The scene's training labels ((H, W) uint8 codes 1-4, 0 none) and their grid, or
    None without them."""
    if scene.training_labels is None:
        return None
    data, label_grid, _ = read_raster(scene.training_labels, field="training_labels")
    return data[0], label_grid


def classify_views(cache: ObservationCache, ctx: ViewContext | None, forest,
                   engine: Engine) -> int:  # fmt: skip
    """Each view's class probabilities per pixel (uint8, 0-255), kept beside the cache
    (a task per view); returns the number of pixels classified."""
    if forest is None:
        return 0
    ctx.forest = forest
    if engine.workers > 1:  # a task per core: the forest's own threads would oversubscribe
        ctx.forest = copy.copy(forest)
        ctx.forest.set_params(n_jobs=1)
    # the cache once to each worker: a fusion in blocks gives every block's (fusion.blocks)
    shared, cache = engine.share(ctx), engine.share(cache)
    return sum(engine.map(classify_view, range(len(ctx.views)), shared, cache,
                          stage="classification"))  # fmt: skip


def classify_view(i: int, ctx: ViewContext, cache: ObservationCache) -> int:
    """Task: view ``i``'s class probabilities, (H*W, 4) uint8, to
    ``cache.probs_path(i)``; returns the number of pixels classified.

    Only the pixels the colour pass reads are classified, the view's visible
    observations (:meth:`ObservationCache.view_pixels`, half of the pixels that see the
    grid on `small`); the others are left 0."""
    camera = ctx.views[i].camera
    observed = cache.view_pixels(i, camera.width * camera.height)
    depth, feats, pixels, _, window = ctx.features(ctx.views[i], ctx.grid, observed)
    probs = np.zeros((depth.size, len(CLASSES)), np.uint8)
    if window is not None:
        p = np.round(predict_proba(ctx.forest, feats) * 255).astype(np.uint8)
        probs[window_pixels(window, pixels, depth.shape[1])] = p
    np.save(cache.probs_path(i), probs)
    return 0 if window is None else len(pixels)


@dataclass
class FusedColours:
    """The colour pass: (H, W, 3) vector median and mean colour, (4, H, W) accumulated
    class probabilities, (H, W) crown sightings' height (NaN where none)."""

    ortho: np.ndarray
    ortho_mean: np.ndarray
    prob_sum: np.ndarray
    crown_z: np.ndarray


def colours_and_classes(
    cache: ObservationCache,
    views,
    with_probs: bool,
    dsm: np.ndarray,
    h: FusedHeights,
    mode: str,
    opts: FusionOptions,
    engine: Engine,
) -> FusedColours:
    """Per cell, the vector median colour and the accumulated class probabilities of the
    top surface's observations; the crown sightings (not in the paper) on the way. A task
    per tile; ``views`` is the engine's handle on the views."""
    grid = cache.grid
    out = FusedColours(
        np.zeros(grid.shape + (3,), np.uint8), np.full(grid.shape + (3,), np.nan, np.float32),
        np.zeros((len(CLASSES),) + grid.shape, np.float32),
        np.full(grid.shape, np.nan, np.float32),
    )  # fmt: skip
    windows = [(slice(r0, r0 + th), slice(c0, c0 + tw)) for r0, c0, th, tw in cache.tiles]
    # each task takes its tile's DSM and top surface along: no whole grid is sent
    items = [(t, dsm[w], h.dsm_upper[w]) for t, w in enumerate(windows)]
    setting = TileColouring(with_probs, mode == "depth maps", opts.projections, opts.seed)
    results = engine.map(tile_colours, items, views, cache, setting, stage="colour_and_class")
    for window, (ortho, ortho_mean, prob_sum, crown_z) in zip(windows, results, strict=True):
        out.ortho[window], out.ortho_mean[window] = ortho, ortho_mean
        out.crown_z[window] = crown_z
        if prob_sum is not None:
            out.prob_sum[(slice(None), *window)] = prob_sum
    return out


@dataclass(frozen=True)
class TileColouring:
    """How :func:`tile_colours` works: with the views' class probabilities or not, with
    the crown sightings (views with depth maps) or not, and the vector median's
    projections and seed."""

    with_probs: bool
    crown_sightings: bool
    projections: int
    seed: int


def tile_colours(item: tuple, views: list, cache: ObservationCache, how: TileColouring):
    """Task: tile ``item[0]``'s (h, w, 3) vector median and mean colour, (4, h, w)
    accumulated class probabilities (None without them) and (h, w) crown sightings'
    height, given the tile's (h, w) DSM ``item[1]`` and upper quantile ``item[2]``."""
    t, dsm, upper = item
    _, _, th, tw = cache.tiles[t]
    n = th * tw
    parts = []
    for i in cache.touching(t):
        local, top, px, z, weight = cache.in_tile(i, t, "cells", "top", "pixels", "z", "weight")
        colour = views[i].read_image().reshape(-1, 3)[px]
        prob = np.load(cache.probs_path(i), mmap_mode="r")[px] if how.with_probs \
            else None  # fmt: skip
        parts.append((local, top, colour, prob, z, weight))
    cells = _joined([p[0] for p in parts], np.int64)
    rel = _joined([p[1] for p in parts], bool)
    colours = _joined([p[2] for p in parts], np.uint8, (3,))
    probs = _joined([p[3] for p in parts], np.uint8, (len(CLASSES),)) if how.with_probs else None
    z, weight = (_joined([p[k] for p in parts], np.float32) for k in (4, 5))
    del parts  # the views' own copies, once joined: this pass sets the peak
    top_z = upper.ravel()
    crown_z = np.full((th, tw), np.nan, np.float32)
    if probs is not None and how.crown_sightings:
        tree = probs[:, CLASSES.index(3)] / np.float32(255)
        crown = crown_sightings(cells, z, weight, tree, dsm.ravel())
        crown_z = crown.reshape(th, tw).astype(np.float32)
        # the crown, not the ground seen beneath it, votes for the cell
        top_z = np.where(np.isfinite(crown), crown, top_z)
    use = top_surface_votes(cells, z, rel, top_z)
    cells, colours = cells[use], colours[use]
    ortho = vector_median(cells, colours, n, n_projections=how.projections, seed=how.seed).reshape(
        th, tw, 3
    )
    ortho_mean = group_mean(cells, colours.astype(np.float32), n).reshape(th, tw, 3)
    prob_sum = None
    if probs is not None:
        p = probs[use].astype(np.float32) / 255.0
        prob_sum = np.stack(
            [np.bincount(cells, p[:, k], minlength=n).reshape(th, tw) for k in range(len(CLASSES))]
        ).astype(np.float32)
    return ortho, ortho_mean.astype(np.float32), prob_sum, crown_z


def _finish(
    c: FusedColours,
    h: FusedHeights,
    dsm,
    dtm,
    spikes,
    holes,
    forest,
    strokes,
    class_source,
    grid: Grid,
    mode: str,
    opts: FusionOptions,
    timer: StageTimer,
    engine: Engine,
    origin: tuple[int, int] = (0, 0),
):
    """Normalised classes with the elevation prior, the class CRF's labels, planar objects
    classed tree made building, the crowns' corrections of the DSM (none of them in the
    paper), the small holes of the ortho filled, the count flagged."""
    median = dsm
    with timer.stage("finish"):
        dsm, ndsm, class_prob, ortho, flat, class_source = _class_confidences(
            c, h, dsm, dtm, holes, forest, strokes, class_source, grid, opts, origin
        )
    with timer.stage("class_crf"):
        classes = contrast_class_crf(class_prob, ortho, dsm, opts.class_crf, engine=engine)
    if opts.class_crf > 0:
        class_source += (
            f"; class.tif: a contrast-sensitive Potts model (omega {opts.class_crf:g}) on "
            "the ortho's colour and the DSM"
        )
    planar = dict.fromkeys(PLANAR_COUNTS, 0)
    if opts.planar_objects:
        with timer.stage("planar_objects"):
            classes, class_prob, planar = planar_roofs_classed_tree(
                classes, class_prob, dsm, ndsm, grid.gsd, opts.seed
            )
        class_source += (
            "; objects classed tree made building in both rasters where planes explain most "
            "of their cells, and roof faces joined to crowns where they continue a building "
            "(fusion.planar_objects; counted in planar_objects_made_building and "
            "roof_faces_made_building)"
        )
    with timer.stage("crowns"):
        crowns = cleared = np.zeros(grid.shape, bool)
        if mode == "depth maps":
            dsm, cleared = sightings_clear_of_buildings(dsm, median, np.isfinite(c.crown_z),
                                                        classes, grid.gsd)  # fmt: skip
            h.dsm_upper[spikes | isolated_spikes(h.dsm_upper, h.count)] = np.nan
            dsm, crowns = crown_tops(dsm, h.dsm_upper, classes, grid.gsd)
            ndsm = (dsm - dtm).astype(np.float32)
        count16 = np.minimum(h.count, np.iinfo(np.int16).max).astype(np.int16)
        count16[holes] = FILLED
    return (dsm, ndsm, class_prob, classes, ortho, count16, crowns, cleared, planar, flat,
            class_source)  # fmt: skip


def _class_confidences(c: FusedColours, h: FusedHeights, dsm, dtm, holes, forest, strokes,
                       class_source, grid: Grid, opts: FusionOptions,
                       origin: tuple[int, int] = (0, 0)):  # fmt: skip
    """The accumulated class confidences normalised, with the elevation prior, ground
    and grass weighed by their colours (:mod:`fusion.flat_colours`) and the raster
    forest; the DSM with the crowns' sightings; the ortho's small holes filled; the
    colour models' record."""
    seen = h.count > 0
    class_prob = c.prob_sum  # normalised in place: the sums are not needed after
    with np.errstate(invalid="ignore", divide="ignore"):
        class_prob /= class_prob.sum(axis=0, keepdims=True)
    # before the elevation prior, which would otherwise damp tree at crowns' rims
    dsm = np.where(np.isfinite(c.crown_z), c.crown_z, dsm)
    ndsm = (dsm - dtm).astype(np.float32)
    class_prob[:, ~seen] = np.nan
    if forest is not None:
        class_prob = elevation_prior(class_prob, ndsm, opts.label_split, copy=False)
        class_source += (
            f"; tree and building damped below {opts.label_split / 2:g} m nDSM, ground "
            f"and grass above {opts.label_split + 2:g} m"
        )
    ortho = fill_small_holes(c.ortho, seen, holes, HOLE_CELLS, origin)
    flat = {"used": False, "reason": "--no-flat-colours, or no training strokes"}
    if strokes is not None:
        flat = weigh_by_stroke_colours(class_prob, ortho, sample_to_grid(*strokes, grid),
                                       opts.seed)  # fmt: skip
        if flat["used"]:
            class_source += "; ground and grass weighed by each cell's colour (flat_colours)"
    class_prob, class_source = _raster_forest(class_prob, class_source, forest, dsm, dtm, ortho,
                                              grid, opts)  # fmt: skip
    return dsm, ndsm, class_prob, ortho, flat, class_source


def _raster_forest(class_prob, class_source, forest, dsm, dtm, ortho, grid: Grid, opts):
    """Without a per-view forest, the forest for label-free rasters gives the classes;
    with --raster-prior, its probabilities multiply the views' (a product of experts)."""
    if forest is not None and not opts.raster_prior:
        return class_prob, class_source
    raster_prob = classify_rasters(synthetic_raster_forest(), dsm, dtm, ortho, grid.gsd)
    if forest is None:
        return raster_prob, (
            "a forest trained on the synthetic city's rasters (nDSM, slope, roughness, "
            "curvature, brightness, greenness): no training labels"
        )
    with np.errstate(invalid="ignore", divide="ignore"):
        prod = class_prob * raster_prob
        class_prob = prod / prod.sum(axis=0, keepdims=True)
    return (
        class_prob,
        class_source + "; multiplied by the raster forest's probabilities (--raster-prior)",
    )


def isolated_spikes(
    dsm: np.ndarray, count: np.ndarray, *, max_count: int = 4, jump: float = 1.0
) -> np.ndarray:
    """(H, W) bool: thinly observed cells that stand alone, spikes or pits.

    A median of a few observations fails when most of them are gross depth errors.
    Such a cell differs by more than ``jump`` metres from at least 7 of its 8
    neighbours, whereas a cell on a real edge shares its height with the neighbours
    on its own side. Cells seen more than ``max_count`` times are trusted.
    """
    alone = close_neighbours(dsm, jump) <= 1  # at least 7 of 8 differ or are unknown
    return np.isfinite(dsm) & (count <= max_count) & alone


def _train(ctx: ViewContext, labels_path, engine: Engine):
    """Train the forest on the training strokes projected into the views.

    A stroke labels the top surface seen from above: a view pixel inherits its label
    only where the pixel's point lies on that surface (within the visibility
    tolerance of the fused DSM), not on a facade or an edge's rounded depth, and only
    where the patch's elevation agrees with the class (:func:`elevation_consistent`).
    A task per view returns its labelled pixels; the samples are drawn here, in view
    order, so that the draw does not depend on the engine.

    Returns
    -------
    forest, number of training pixels, number of labelled pixels dropped by elevation
    """
    opts = ctx.opts
    data, label_grid, _ = read_raster(labels_path, field="training_labels")
    labels = (ctx.rasters.keep("training_labels", data[0]), label_grid)  # a file, mapped
    rng = np.random.default_rng(opts.seed)
    # a spread subset of views gives as varied samples as all of them, in less time
    step = max(1, int(np.ceil(len(ctx.views) / opts.training_views)))
    chosen_views = list(range(0, len(ctx.views), step))
    per_view = max(200, opts.samples_per_class // len(chosen_views))
    X, y, n_dropped = [], [], 0
    shared = engine.share(ctx)
    for feats, lab, dropped in engine.map(labelled_pixels, chosen_views, shared, labels,
                                          stage="training"):  # fmt: skip
        n_dropped += dropped
        if len(lab) == 0:
            continue
        chosen = []
        for k in CLASSES:
            idx = np.flatnonzero(lab == k)
            if len(idx):
                chosen.append(rng.choice(idx, min(per_view, len(idx)), replace=False))
        chosen = np.concatenate(chosen)
        X.append(feats[chosen])
        y.append(lab[chosen])
    if not X:
        raise InputError(labels_path, None, "no training label falls inside any view")
    X, y = np.concatenate(X), np.concatenate(y)
    forest = train_forest(X, y, n_trees=opts.n_trees, max_depth=opts.max_depth, seed=opts.seed)
    return forest, len(y), n_dropped


def labelled_pixels(i: int, ctx: ViewContext, labels: tuple) -> tuple:
    """Task: view ``i``'s labelled pixels: their features and labels, and the number of
    labelled pixels dropped by elevation. ``labels`` is (label raster's .npy file, its
    grid).

    Only the pixels on a stroke are described (strokes cover 2.2 % of `small`'s cells): their
    features are those they have among all the view's (:func:`view_features`)."""

    def on_stroke(pixels, xyz):
        return stroke_labels(xyz, labels, ctx) > 0

    _, feats, pixels, xyz, window = ctx.features(ctx.views[i], labels[1], on_stroke)
    if window is None:
        return np.zeros((0, 0), np.float32), np.zeros(0, np.uint8), 0  # the view sees no label
    lab = stroke_labels(xyz, labels, ctx)
    agree = elevation_consistent(lab, feats[:, MEAN_ELEVATION], ctx.opts.label_split)
    lab[~agree] = 0
    keep = np.flatnonzero(lab > 0)
    return feats[keep], lab[keep], int((~agree).sum())


def stroke_labels(xyz: np.ndarray, labels: tuple, ctx: ViewContext) -> np.ndarray:
    """(N,) uint8 class of the stroke under each point (N, 3), 0 where none, or where the
    point is not on the fused top surface (within the DSM's tolerance): a facade's or a
    rounded edge's point would teach its stroke's class to what lies below the roof."""
    label_file, label_grid = labels
    label_raster = np.load(label_file, mmap_mode="r")
    r, c = label_grid.cell_index(xyz[:, 0], xyz[:, 1])
    inside = label_grid.contains(r, c)
    lab = np.zeros(len(xyz), np.uint8)
    lab[inside] = label_raster[r[inside], c[inside]]
    gr, gc = ctx.grid.cell_index(xyz[:, 0], xyz[:, 1], clip=True)
    with np.errstate(invalid="ignore"):
        on_top = np.abs(xyz[:, 2] - ctx.rasters.read("dsm")[gr, gc]) < ctx.opts.tolerance
    lab[~on_top] = 0
    return lab
